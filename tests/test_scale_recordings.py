"""Per-keyframe scale records in the recordings (issue #33): ``run --mcap`` and ``run --rerun``
carry the learned and the ground scale, their disagreement, the back end's scale σ and the health
flag, read back with the ``mcap`` reader / rerun's own reader; ``ScaleHealth`` emits one
``ScaleHealthUpdated`` per measurement it stores."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from metricslam.slam.events import EventBus, GroundScaleMeasured, ScaleHealthUpdated, ScaleMeasured, scale_record
from metricslam.slam.ground.health import ScaleHealth
from metricslam_cli.main import main
from tests.test_mcap_recording import read_mcap

SCALE_FLAGS = ["--scale-sources", "learned,ground", "--mount-height", "1.65"]  # the renderer's height


def _learned(kf_id: int, scale: float) -> ScaleMeasured:
    return ScaleMeasured(kf_id, 3 * kf_id, 1000 * kf_id, np.zeros((5, 2)), np.ones(5), np.ones(5),
                         np.full(5, scale), None, (64, 32))


def _ground(kf_id: int, scale: float) -> GroundScaleMeasured:
    return GroundScaleMeasured(kf_id, 3 * kf_id, 1000 * kf_id, 1.65 / scale, scale, 0.05, True)


def test_scale_health_emits_one_record_per_stored_measurement():
    bus, records = EventBus(), []
    bus.subscribe(records.append, ScaleHealthUpdated)
    ScaleHealth().attach(bus)
    bus.emit(_learned(1, 2.0))
    bus.emit(GroundScaleMeasured(1, 3, 1000, float("nan"), float("nan"), float("inf"), False, "no road"))
    bus.emit(_ground(1, 1.6))
    bus.emit(_learned(2, 2.2))
    assert [(r.kf_id, r.frame_index, r.t_ns) for r in records] == [(1, 3, 1000), (1, 3, 1000), (2, 6, 2000)]
    first, both, second = records
    assert first.learned_scale == pytest.approx(2.0) and np.isnan(first.ground_scale)
    assert np.isnan(first.disagreement_log) and np.isnan(first.learned_spread_log)
    assert both.ground_scale == pytest.approx(1.6)
    assert both.disagreement_log == pytest.approx(np.log(2.0 / 1.6))
    assert second.learned_spread_log == pytest.approx(np.std(np.log([2.0, 2.2])))
    assert not any(r.warning for r in records)

    class Backend:
        def scale_sigma_log(self):
            return 0.04

    assert scale_record(both, Backend())["sigma_log"] == 0.04
    assert scale_record(both)["sigma_log"] is None


def _float64(data: bytes) -> float:
    return struct.unpack_from("<d", data, 4)[0]  # after the 4-byte CDR encapsulation header


def test_run_mcap_records_each_keyframes_scale_numbers(synth_sequence, tmp_path: Path) -> None:
    seq_dir = synth_sequence(40, seed=3, path="loop")
    mcap_path = tmp_path / "run.mcap"
    assert main(["run", str(seq_dir), "--out", str(tmp_path / "est.txt"), "--deterministic", "--no-progress",
                 "--mcap", str(mcap_path), *SCALE_FLAGS]) == 0
    topics = read_mcap(mcap_path)
    (base,) = {t.rsplit("/", 1)[0] for t in topics if t.endswith("/pose")}
    scale = {name: topics.get(f"{base}/scale/{name}", []) for name in
             ("learned", "ground", "disagreement_log", "sigma_log", "warning")}
    for name, msgs in scale.items():
        assert msgs, f"no {name} messages; topics: {sorted(topics)}"
        expected = "std_msgs/msg/Bool" if name == "warning" else "std_msgs/msg/Float64"
        assert {m[3] for m in msgs} == {expected}
    frame_times = {m[0] for m in topics[f"{base}/pose"]}
    assert {m[0] for m in scale["warning"]} <= frame_times  # stamped with their keyframe's time
    assert len(scale["warning"]) >= len(scale["ground"]) >= 5
    learned = np.array([_float64(m[2]) for m in scale["learned"]])
    ground = np.array([_float64(m[2]) for m in scale["ground"]])
    assert np.all(learned > 0) and np.all(ground > 0)
    # both measure metres per VO unit of the same keyframes: on a rendered street they agree
    assert abs(np.median(np.log(learned)) - np.median(np.log(ground))) < 0.3
    assert all(np.isfinite(_float64(m[2])) and _float64(m[2]) > 0 for m in scale["sigma_log"])
    assert {m[2][4] for m in scale["warning"]} <= {0, 1}


@pytest.mark.slow
def test_run_rerun_records_each_keyframes_scale_numbers(synth_sequence, tmp_path: Path) -> None:
    pytest.importorskip("rerun", reason="rerun-sdk is the optional viz extra")
    from rerun.chunk import RrdReader

    seq_dir = synth_sequence(40, seed=3, path="loop")
    rrd = tmp_path / "run.rrd"
    assert main(["run", str(seq_dir), "--out", str(tmp_path / "est.txt"), "--deterministic", "--no-progress",
                 "--rerun", str(rrd), *SCALE_FLAGS]) == 0
    paths = {chunk.entity_path for chunk in RrdReader(rrd).stream()}
    cam = Path(seq_dir).name
    for name in ("learned", "ground", "disagreement_log", "sigma_log", "warning"):
        assert f"/scale/{cam}/{name}" in paths, (name, sorted(paths))
