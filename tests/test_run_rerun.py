"""``metricslam run --rerun out.rrd``: an offline recording with the SLAM service's entities
(camera, image, trajectory, keyframes, landmarks, keyframe depth from the back end's
ScaleMeasured events), read back with rerun's own reader; a clear error without rerun-sdk."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from metricslam.errors import ConfigError
from metricslam_cli.main import main


@pytest.mark.slow
def test_run_writes_a_recording_with_the_service_entities(shared_data: Path, tmp_path: Path) -> None:
    pytest.importorskip("rerun", reason="rerun-sdk is the optional viz extra")
    from rerun.chunk import RrdReader

    seq = shared_data / "kitti_odometry" / "sequences" / "06"
    if not seq.is_dir():
        pytest.skip(f"{seq} is absent")
    rrd = tmp_path / "rec" / "run.rrd"
    rc = main(["run", str(seq), "--out", str(tmp_path / "est.txt"), "--deterministic", "--max-frames", "30",
               "--no-progress", "--rerun", str(rrd)])
    assert rc == 0
    paths = {chunk.entity_path for chunk in RrdReader(rrd).stream()}
    for entity in ("camera", "camera/image", "trajectory", "keyframes", "landmarks"):
        assert f"/world/06/{entity}" in paths, (entity, sorted(paths))
    assert "/world/keyframe_depth" in paths, sorted(paths)


def test_missing_rerun_sdk_is_a_clear_error(monkeypatch) -> None:
    from metricslam_cli.run_cmd import open_recording

    monkeypatch.setitem(sys.modules, "rerun", None)  # import rerun -> ImportError
    with pytest.raises(ConfigError, match=r"viz extra.*pip install"):
        open_recording("x.rrd")


def test_run_refuses_a_live_viewer_target_before_reading(tmp_path: Path, capsys) -> None:
    rc = main(["run", str(tmp_path / "no_such_sequence"), "--out", str(tmp_path / "e.txt"), "--rerun", "web"])
    assert rc == 1
    assert "ending in .rrd" in capsys.readouterr().err
