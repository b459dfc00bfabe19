"""One clip, three dataset layouts, one calibration file: KITTI 06 as it is, and copies of it laid
out as a TUM RGB-D folder and as an EuRoC folder (images linked, timestamps and ground truth in
each format), each run with ``metricslam run --deterministic --calib calib.yaml``. The three
trajectories must agree (scale within 0.5 %, measured with the evaluator), ``eval`` must take
the TUM-format outputs against TUM and EuRoC ground truth (files and folders), and without ``--calib`` the TUM copy
(whose name names no Freiburg camera) must be refused with an actionable error.

Nothing is written into ../shared/data: the copies live in a temporary folder.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from metricslam.calibration import make_calibration
from metricslam.datasets import KittiOdometry
from metricslam.evaluation import evaluate_files
from metricslam.geometry import so3
from metricslam.trajectory.io import ns_to_seconds_text, write_tum

CLI = [sys.executable, "-m", "metricslam_cli.main"]
TUM_T0_NS = 1_305_031_102_175_304_000   # a TUM-like epoch: stamps survive the seconds text exactly
EUROC_T0_NS = 1_403_636_579_763_555_584
#: VO preset of the footage (the copies would otherwise get the tum / euroc preset by layout)
RUN_ARGS = ["--deterministic", "--preset", "kitti", "--no-progress"]


def _link(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.symlink_to(src.resolve())


def make_tum_copy(seq: KittiOdometry, root: Path) -> Path:
    t_ns = TUM_T0_NS + seq.t_ns
    lines = ["# color images (KITTI 06 laid out as TUM RGB-D)", "# timestamp filename"]
    for path, t in zip(seq.image_paths, t_ns):
        name = f"rgb/{ns_to_seconds_text(int(t))}.png"
        _link(path, root / name)
        lines.append(f"{ns_to_seconds_text(int(t))} {name}")
    (root / "rgb.txt").write_text("\n".join(lines) + "\n")
    write_tum(root / "groundtruth.txt", t_ns, seq.T_world_cam_gt)
    return root


def make_euroc_copy(seq: KittiOdometry, root: Path, wrong_K: np.ndarray) -> Path:
    """EuRoC layout with T_BS = identity (the body is the camera) and, on purpose, intrinsics in
    sensor.yaml that are 10 % off: ``--calib`` has to win over them."""
    cam = root / "mav0" / "cam0"
    t_ns = EUROC_T0_NS + seq.t_ns
    rows = ["#timestamp [ns],filename"]
    for path, t in zip(seq.image_paths, t_ns):
        _link(path, cam / "data" / f"{t}.png")
        rows.append(f"{t},{t}.png")
    (cam / "data.csv").write_text("\n".join(rows) + "\n")
    c = seq.camera
    (cam / "sensor.yaml").write_text(
        "%YAML:1.0\nsensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n"
        f"  data: {np.eye(4).reshape(-1).tolist()}\nrate_hz: 10\nresolution: [{c.width_px}, {c.height_px}]\n"
        f"camera_model: pinhole\nintrinsics: [{wrong_K[0, 0]}, {wrong_K[1, 1]}, {wrong_K[0, 2]}, {wrong_K[1, 2]}]\n"
        "distortion_model: radial-tangential\ndistortion_coefficients: [0.0, 0.0, 0.0, 0.0]\n")
    gt = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"]
    for t, T in zip(t_ns, seq.T_world_cam_gt):
        x, y, z, w = so3.to_quat_xyzw(so3.project_to_so3(T[:3, :3]))
        gt.append(f"{t},{T[0, 3]:.9f},{T[1, 3]:.9f},{T[2, 3]:.9f},{w:.12f},{x:.12f},{y:.12f},{z:.12f}")
    (root / "mav0" / "state_groundtruth_estimate0").mkdir(parents=True)
    (root / "mav0" / "state_groundtruth_estimate0" / "data.csv").write_text("\n".join(gt) + "\n")
    return root


def metricslam(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(CLI + list(args), capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def runs(shared_data: Path, tmp_path_factory) -> dict:
    kitti = shared_data / "kitti_odometry" / "sequences" / "06"
    gt = shared_data / "kitti_odometry" / "poses" / "06.txt"
    if not (kitti / "image_0").is_dir() or not gt.is_file():
        pytest.skip(f"KITTI odometry 06 (images and {gt}) is absent")
    d = tmp_path_factory.mktemp("formats")
    seq = KittiOdometry(kitti, poses_file=gt, load_right=False)
    calib = make_calibration(seq.camera.K, seq.camera.width_px, seq.camera.height_px, source="KITTI 06 P0")
    (d / "calib.yaml").write_text(calib.to_yaml())
    wrong_K = seq.camera.K @ np.diag([1.1, 1.1, 1.0])
    folders = {"kitti": kitti, "tum": make_tum_copy(seq, d / "kitti06_tum"),
               "euroc": make_euroc_copy(seq, d / "kitti06_euroc", wrong_K)}
    out = {"dir": d, "gt": gt, "folders": folders, "t_ns": seq.t_ns}
    for name, folder in folders.items():
        est = d / (f"{name}.txt" if name == "kitti" else f"{name}.tum")
        fmt = "kitti" if name == "kitti" else "tum"
        r = metricslam("run", str(folder), "--calib", str(d / "calib.yaml"), "--format", fmt,
                       "--out", str(est), *RUN_ARGS)
        assert r.returncode == 0, r.stderr[-3000:]
        out[name] = est
    return out


def test_all_three_layouts_give_the_same_metric_trajectory(runs) -> None:
    d = runs["dir"]
    kitti = evaluate_files(runs["gt"], runs["kitti"]).result
    tum = evaluate_files(runs["folders"]["tum"] / "groundtruth.txt", runs["tum"]).result
    euroc = evaluate_files(runs["folders"]["euroc"], runs["euroc"]).result
    assert tum.n_frames == euroc.n_frames == kitti.n_frames == 51
    for other in (tum, euroc):
        assert abs(other.scale_ratio / kitti.scale_ratio - 1.0) < 0.005, (kitti.scale_ratio, other.scale_ratio)
    # and directly against each other: the KITTI run's poses, time-stamped, as the reference
    times = d / "times_tum.txt"
    times.write_text("".join(ns_to_seconds_text(int(t)) + "\n" for t in TUM_T0_NS + runs["t_ns"]))
    pair = evaluate_files(runs["kitti"], runs["tum"], gt_times=times).result
    assert abs(pair.scale_ratio - 1.0) < 0.005 and pair.ate_rmse_m < 0.05 * pair.path_length_m
    (d / "agreement.json").write_text(json.dumps(
        {"scale_ratio": {"kitti": kitti.scale_ratio, "tum": tum.scale_ratio, "euroc": euroc.scale_ratio},
         "tum_vs_kitti": {"scale_ratio": pair.scale_ratio, "ate_rmse_m": pair.ate_rmse_m}}, indent=2))


def test_eval_takes_tum_estimates_against_tum_and_euroc_ground_truth(runs) -> None:
    euroc_csv = runs["folders"]["euroc"] / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    cases = [(runs["folders"]["tum"] / "groundtruth.txt", runs["tum"]), (runs["folders"]["tum"], runs["tum"]),
             (runs["folders"]["euroc"], runs["euroc"]), (euroc_csv, runs["euroc"])]
    for i, (gt, est) in enumerate(cases):
        out = runs["dir"] / f"eval_{i}.json"
        r = metricslam("eval", "--gt", str(gt), "--est", str(est), "--json", str(out))
        assert r.returncode == 0, r.stderr
        m = json.loads(out.read_text())
        assert m["n_frames"] == 51 and 0.8 < m["scale_ratio"] < 1.2, m
    # a TUM estimate against KITTI ground truth needs the frames' times
    r = metricslam("eval", "--gt", str(runs["gt"]), "--est", str(runs["tum"]))
    assert r.returncode == 1 and "--gt-times" in r.stderr


def test_tum_folder_without_calibration_is_refused(runs) -> None:
    r = metricslam("run", str(runs["folders"]["tum"]), "--out", str(runs["dir"] / "x.tum"), *RUN_ARGS)
    assert r.returncode == 1, r.stdout
    assert "--calib" in r.stderr and "Freiburg" in r.stderr and "Traceback" not in r.stderr
