"""``metricslam eval`` as a user runs it: the installed console script in a subprocess."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from metricslam.geometry import se3
from metricslam.trajectory.io import write_kitti_poses, write_tum

SCRIPT = Path(sys.executable).parent / "metricslam"


def run(*args: str) -> subprocess.CompletedProcess:
    cmd = [str(SCRIPT)] if SCRIPT.exists() else [sys.executable, "-m", "metricslam_cli.main"]
    return subprocess.run(cmd + ["eval", *args], capture_output=True, text=True, timeout=120)


def trajectory(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = [np.eye(4)]
    for _ in range(n - 1):
        T.append(T[-1] @ se3.exp(np.array([0, rng.normal(0, 0.02), 0, 0, 0, 1.0])))
    return np.stack(T)


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("eval")
    gt = trajectory(250, 1)
    est = gt.copy()
    est[:, :3, 3] *= 1.1
    write_kitti_poses(d / "gt.txt", gt)
    write_kitti_poses(d / "est.txt", est)
    gt2 = trajectory(60, 2)
    write_kitti_poses(d / "gt2.txt", gt2)
    write_kitti_poses(d / "est2.txt", gt2)
    t_ns = 10**18 + np.arange(250, dtype=np.int64) * 100_000_000
    write_tum(d / "gt_tum.txt", t_ns, gt)
    write_tum(d / "est_tum.txt", t_ns[::2] + 1_000_000, est[::2])
    return {p.stem: p for p in d.iterdir()} | {"dir": d}


def test_eval_prints_a_table_and_writes_json_and_plot(files):
    out_json, out_png = files["dir"] / "out" / "m.json", files["dir"] / "out" / "m.png"
    r = run("--gt", str(files["gt"]), "--est", str(files["est"]), "--json", str(out_json),
            "--plot", str(out_png))
    assert r.returncode == 0, r.stderr
    assert "t_rel %" in r.stdout and "ATE SE3 m" in r.stdout and "1.1000" in r.stdout
    m = json.loads(out_json.read_text())
    assert m["scale_ratio"] == pytest.approx(1.1) and m["scale_error_pct"] == pytest.approx(10.0)
    assert m["n_frames"] == 250 and m["t_rel_lengths_m"] == [100.0, 200.0]
    assert m["ate_rmse_sim3_m"] == pytest.approx(0.0, abs=1e-6)
    assert out_png.read_bytes()[:4] == b"\x89PNG"


def test_eval_several_sequences_reports_pooled_and_mean(files):
    out_json = files["dir"] / "multi.json"
    r = run("--gt", str(files["gt"]), "--est", str(files["est"]),
            "--gt", str(files["gt2"]), "--est", str(files["est2"]), "--json", str(out_json))
    assert r.returncode == 0, r.stderr
    assert "pooled" in r.stdout and "mean of sequences" in r.stdout and "10..50 m" in r.stdout
    m = json.loads(out_json.read_text())
    assert [s["name"] for s in m["per_sequence"]] == ["est", "est2"]
    assert m["n_frames"] == 310 and m["mean_of_sequences"]["scale_ratio"] == pytest.approx(1.05)


def test_eval_tum_files_are_associated_by_time(files):
    out_json = files["dir"] / "tum.json"
    r = run("--gt", str(files["gt_tum"]), "--est", str(files["est_tum"]), "--json", str(out_json))
    assert r.returncode == 0, r.stderr
    m = json.loads(out_json.read_text())
    assert m["n_frames"] == 125 and m["scale_ratio"] == pytest.approx(1.1)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--gt", "{gt}", "--est", "{gt2}"], "poses"),
        (["--gt", "{gt}", "--est", "{missing}"], "does not exist"),
        (["--gt", "{gt}", "--est", "{est_tum}"], "same format"),
        (["--gt", "{gt}", "--gt", "{gt2}", "--est", "{est}"], "in pairs"),
    ],
)
def test_eval_user_errors_exit_1_with_a_message(files, args, message):
    paths = {k: str(v) for k, v in files.items()} | {"missing": str(files["dir"] / "nope.txt")}
    r = run(*[a.format(**paths) for a in args])
    assert r.returncode == 1, r.stdout
    assert "metricslam eval: error:" in r.stderr and message in r.stderr
    assert "Traceback" not in r.stderr
