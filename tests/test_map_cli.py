"""``metricslam map info`` / ``map keyframes`` (docs/maps.md, "Inspecting a map"): a saved map is
checked and described without running SLAM, its keyframe poses written for plotting or ``eval``;
a corrupt map or a file that is not one is the one-line error a run gives, exit code 1."""

from __future__ import annotations

import json

import numpy as np
import pytest

from metricslam.slam.map.format import save_map
from metricslam.trajectory.io import read_kitti_poses, read_tum
from metricslam_cli.main import main
from tests.test_map_format import random_map


@pytest.fixture()
def saved_map(tmp_path):
    saved = random_map(4, n_kf=9)
    kf = saved.arrays["keyframes"]
    kf["kf_id"][:] = np.arange(9)
    kf["T_map_kf"][:] = np.eye(4)
    kf["T_map_kf"][:, 0, 3] = np.arange(9) * 2.0  # keyframes 2 m apart along x
    kf["t_ns"][:] = np.arange(9) * 500_000_000
    kf["scale_kf"][:], kf["scale_measured_median"][:] = 2.0, 2.2  # the network reads 10 % more
    kf["scale_measured_median"][0], kf["scale_factors"][:] = np.nan, 40  # keyframe 0 unmeasured
    saved.source["extended_by"] = [{"sequence": "day2", "mode": "metric"}]
    save_map(saved, tmp_path / "m")
    return saved, tmp_path / "m"


def test_info_describes_the_map(saved_map, capsys):
    saved, path = saved_map
    assert main(["map", "info", str(path), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert (s["keyframes"], s["landmarks"], s["sessions"], s["metric"]) == (9, len(saved.arrays["landmarks"]["p_map_m"]), 2, True)
    assert s["vocabulary_id"] == saved.vocabulary_id and s["depth_model_id"] == saved.depth_model_id
    assert s["time_span_s"] == 4.0 and s["box_max"][0] - s["box_min"][0] == 16.0
    assert (s["keyframes_scale_measured"], s["scale_factors"]) == (8, 360)
    assert np.isclose(s["scale_gap_log_median"], np.log(1.1)) and np.isclose(s["scale_gap_log_p90"], np.log(1.1))
    assert s["bytes"] == sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
    assert main(["map", "info", str(path)]) == 0
    text = capsys.readouterr().out
    assert "9 keyframes" in text and "extended by day2" in text and "16.0 x 0.0 x 0.0 m box" in text
    assert "8 of 9 keyframes measured (360 scale factors)" in text and "10.0 % apart at the median" in text


def test_keyframes_writes_the_map_frame_poses(saved_map, tmp_path):
    saved, path = saved_map
    order = np.arange(9)
    assert main(["map", "keyframes", str(path), "--out", str(tmp_path / "kf.txt")]) == 0
    t_ns, T = read_tum(tmp_path / "kf.txt")
    np.testing.assert_array_equal(t_ns, saved.arrays["keyframes"]["t_ns"][order])
    np.testing.assert_allclose(T, saved.arrays["keyframes"]["T_map_kf"][order], atol=1e-8)
    assert main(["map", "keyframes", str(path), "--out", str(tmp_path / "kf.kitti"), "--format", "kitti"]) == 0
    np.testing.assert_allclose(read_kitti_poses(tmp_path / "kf.kitti"), T, atol=1e-8)


def test_keyframes_of_sessions_on_their_own_clocks_are_kitti_only(tmp_path, capsys):
    saved = random_map(5, n_kf=6)
    kf = saved.arrays["keyframes"]
    kf["kf_id"][:], kf["t_ns"][:] = np.arange(6), [0, 1, 2, 0, 1, 2]  # session 2 restarts its clock
    kf["scale_measured_median"][:] = np.nan  # no depth network (a --no-scale map)
    save_map(saved, tmp_path / "m")
    assert main(["map", "info", str(tmp_path / "m")]) == 0
    assert "learned scale: no keyframe measured" in capsys.readouterr().out
    assert main(["map", "keyframes", str(tmp_path / "m"), "--out", str(tmp_path / "kf.txt")]) == 1
    assert "use --format kitti" in capsys.readouterr().err and not (tmp_path / "kf.txt").exists()
    assert main(["map", "keyframes", str(tmp_path / "m"), "--out", str(tmp_path / "kf.txt"), "--format", "kitti"]) == 0


def test_a_corrupt_map_or_a_file_is_one_error_line(saved_map, tmp_path, capsys):
    _, path = saved_map
    blob = (path / "keyframes" / "T_map_kf.npy").read_bytes()
    (path / "keyframes" / "T_map_kf.npy").write_bytes(blob[:-8])  # truncated
    assert main(["map", "info", str(path)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "T_map_kf.npy does not match its checksum" in err[0]
    (tmp_path / "f.txt").write_text("x")
    assert main(["map", "keyframes", str(tmp_path / "f.txt"), "--out", str(tmp_path / "o.txt")]) == 1
    assert "is a file; a map is a folder" in capsys.readouterr().err
    assert main(["map", "keyframes", str(path.parent / "m"), "--out", str(tmp_path / "f.txt" / "kf.txt")]) == 1
    err = capsys.readouterr().err.strip().splitlines()  # (the map is corrupt: checked first)
    assert len(err) == 1


def test_an_output_that_cannot_be_written_is_one_error_line(saved_map, tmp_path, capsys):
    _, path = saved_map
    (tmp_path / "f.txt").write_text("x")
    assert main(["map", "keyframes", str(path), "--out", str(tmp_path / "f.txt" / "kf.txt")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--out" in err[0] and "is a file, not a folder" in err[0]


def test_it_needs_no_extra(saved_map):
    """A bare ``pip install metricslam`` inspects maps: every module an extra adds is unimportable."""
    import subprocess
    import sys

    from tests.test_core_purity import RUN_WITHOUT_EXTRAS

    _, path = saved_map
    proc = subprocess.run([sys.executable, "-c", RUN_WITHOUT_EXTRAS, "map", "info", str(path), "--json"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert json.loads(proc.stdout)["keyframes"] == 9
