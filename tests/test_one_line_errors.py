"""Issue #32 "Never a silently wrong trajectory": a mistake the user can fix is one error line
(exit code != 0, no traceback, no pydantic documentation URL), said before the work starts; a
metric run whose learned scale never engaged says so and fails.

Real processes throughout: what is checked is what a user sees on the terminal.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from metricslam_slam.supervisor.launcher import Child, free_port

CLI = [sys.executable, "-m", "metricslam_cli.main"]
BINARY = b"\x89PNG\r\n\x1a\n\xff\xfe\x00\x01 not a calibration"


def metricslam(*args: str, env: dict[str, str] | None = None, timeout: float = 120) -> subprocess.CompletedProcess:
    full_env = {**os.environ, **(env or {})}
    return subprocess.run(CLI + list(args), capture_output=True, text=True, timeout=timeout, env=full_env)


def error_line(proc: subprocess.CompletedProcess, command: str, *names: str) -> str:
    """The one ``metricslam <command>: error: …`` line of a failed run, naming each of ``names``."""
    assert proc.returncode != 0, proc.stdout[-2000:]
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert "errors.pydantic.dev" not in proc.stderr + proc.stdout
    lines = [line for line in proc.stderr.splitlines() if line.startswith(f"metricslam {command}: error: ")]
    assert len(lines) == 1, proc.stderr[-3000:]
    for name in names:
        assert name in lines[0], (name, lines[0])
    return lines[0]


@pytest.fixture(scope="module")
def kitti06(shared_data) -> Path:
    seq = shared_data / "kitti_odometry" / "sequences" / "06"
    if not (seq / "image_0").is_dir():
        pytest.skip(f"KITTI odometry sequence 06 is absent from {shared_data}")
    return seq


# --- A: a model that cannot be loaded; learned scale that never engaged -------------------------

@pytest.mark.data
def test_run_with_a_missing_model_fails_before_the_first_frame(kitti06, tmp_path) -> None:
    out = tmp_path / "est.txt"
    proc = metricslam("run", str(kitti06), "--model", str(tmp_path / "typo.onnx"), "--out", str(out),
                      "--no-progress")
    error_line(proc, "run", "typo.onnx", "does not exist", "--model")
    assert proc.stdout == "" and not out.exists()
    not_onnx = tmp_path / "model.onnx"
    not_onnx.write_text("not a network\n")
    proc = metricslam("run", str(kitti06), "--model", str(not_onnx), "--out", str(out), "--no-progress")
    error_line(proc, "run", str(not_onnx))
    assert proc.stdout == "" and not out.exists()


@pytest.mark.data
def test_a_metric_run_whose_scale_never_engaged_says_so_and_fails(kitti06, tmp_path) -> None:
    """Learned scale that never reaches the graph's threshold: the files are written, the summary
    says ``NOT metric``, the exit code is 1; the same run with --no-scale asked for that."""
    out, stats = tmp_path / "est.txt", tmp_path / "stats.json"
    never = {"METRICSLAM_GRAPH__MIN_SCALE_FACTORS_ESTABLISHED": "1000000"}
    args = ["run", str(kitti06), "--out", str(out), "--json", str(stats), "--max-frames", "20",
            "--deterministic", "--no-progress"]
    proc = metricslam(*args, env=never)
    error_line(proc, "run", "never engaged", str(out), "not metric", "--no-scale")
    assert proc.returncode == 1
    assert "scale: NOT metric" in proc.stdout, proc.stdout
    assert len(out.read_text().splitlines()) == 20
    assert json.loads(stats.read_text())["scale_engaged"] is False
    proc = metricslam(*args, "--no-scale", env=never)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "NOT metric" not in proc.stdout


@pytest.mark.data
@pytest.mark.slow
def test_the_default_model_still_engages_on_kitti_06(kitti06, shared_data, tmp_path) -> None:
    out, stats, metrics = tmp_path / "est.txt", tmp_path / "stats.json", tmp_path / "eval.json"
    proc = metricslam("run", str(kitti06), "--out", str(out), "--json", str(stats), "--deterministic",
                      "--no-progress", timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "scale: metric from frame" in proc.stdout, proc.stdout
    assert json.loads(stats.read_text())["scale_engaged"] is True
    gt = shared_data / "kitti_odometry" / "poses" / "06.txt"
    if gt.is_file():
        assert metricslam("eval", "--gt", str(gt), "--est", str(out), "--json", str(metrics)).returncode == 0
        assert json.loads(metrics.read_text())["scale_error_pct"] < 15  # a missing model gave 57


# --- B: one-line errors ------------------------------------------------------------------------

@pytest.mark.parametrize("command", ["run", "replay", "camera", "depth"])
def test_a_binary_calibration_file_is_one_line(command, tmp_path) -> None:
    calib = tmp_path / "calib.yaml"
    calib.write_bytes(BINARY)
    seq = tmp_path / "no_such_sequence"
    image = tmp_path / "image.png"
    cv2.imwrite(str(image), np.full((48, 64), 128, np.uint8))
    args = {"run": ["run", str(seq), "--out", str(tmp_path / "est.txt")],
            "replay": ["replay", str(seq)],
            "camera": ["camera", "--device", "99"],
            "depth": ["depth", str(image), "--out", str(tmp_path / "d.npy")]}[command]
    proc = metricslam(*args, "--calib", str(calib))
    error_line(proc, command, str(calib), "not a text file", "UTF-8")


def test_a_calibration_error_has_no_pydantic_boilerplate(tmp_path) -> None:
    calib = tmp_path / "calib.yaml"
    calib.write_text("fx: 500\nfy: 500\ncx: 320\ncy: 240\nwidth: 640\nheight: 480\n"
                     "distortion_model: radtan\ndistortion_coefficients: [0.1, 0.01, 0.001]\n")
    proc = metricslam("run", str(tmp_path / "seq"), "--out", str(tmp_path / "est.txt"), "--calib", str(calib))
    error_line(proc, "run", str(calib), "radtan", "coefficients")


@pytest.mark.data
def test_run_refuses_an_output_path_it_cannot_write_before_processing(kitti06, tmp_path) -> None:
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    cases = [("--out", tmp_path, "is a folder"), ("--out", a_file / "est.txt", "is a file, not a folder"),
             ("--json", tmp_path, "is a folder")]
    for flag, path, why in cases:
        out = str(path) if flag == "--out" else str(tmp_path / "est.txt")
        extra = ["--json", str(path)] if flag == "--json" else []
        t0 = time.monotonic()
        proc = metricslam("run", str(kitti06), "--out", out, *extra, "--no-progress", "--deterministic")
        error_line(proc, "run", flag, str(path), why)
        assert "frames," not in proc.stdout  # refused before the sequence was processed
        assert time.monotonic() - t0 < 30


@pytest.mark.parametrize("variable, value, field", [("SLAM_STATUS_PERIOD_S", "abc", "status_period_s"),
                                                     ("SLAM_MAX_CAMERAS", "-1", "max_cameras"),
                                                     ("SLAM_ROS2", "maybe", "ros2")])
def test_an_invalid_slam_variable_is_one_line(variable, value, field) -> None:
    proc = metricslam("slam-service", "--zenoh-endpoint", f"tcp/127.0.0.1:{free_port()}",
                      env={variable: value}, timeout=60)
    error_line(proc, "slam-service", variable, field, repr(value))
    assert "READY" not in proc.stdout


def test_depth_and_metricslam_variables_are_one_line_without_a_url(tmp_path) -> None:
    proc = metricslam("depth-service", "--port", str(free_port()), env={"DEPTH_MAX_QUEUE": "-1"}, timeout=60)
    error_line(proc, "depth-service", "DEPTH_MAX_QUEUE", "greater than or equal to 0")
    proc = metricslam("run", str(tmp_path / "seq"), "--out", str(tmp_path / "est.txt"),
                      env={"METRICSLAM_GRAPH__ODOM_SIGMA": "1"})
    error_line(proc, "run", "METRICSLAM_", "graph.odom_sigma", "not permitted")


def test_up_refuses_an_unknown_preset_before_starting_anything() -> None:
    port = free_port()
    proc = metricslam("up", "--no-scale", "--zenoh-endpoint", f"tcp/127.0.0.1:{port}", "--preset", "banana",
                      timeout=60)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "argument --preset: invalid choice: 'banana'" in proc.stderr.splitlines()[-1], proc.stderr
    assert "ready" not in proc.stdout  # not even the router was started


def test_up_refuses_a_bad_config_before_starting_anything(tmp_path) -> None:
    config = tmp_path / "bad.yaml"
    config.write_text("graph:\n  no_such_field: 1\n")
    proc = metricslam("up", "--no-scale", "--zenoh-endpoint", f"tcp/127.0.0.1:{free_port()}",
                      "--config", str(config), timeout=60)
    error_line(proc, "up", str(config), "no_such_field")
    assert "ready" not in proc.stdout


def test_up_prints_the_last_lines_of_a_child_that_failed_to_start() -> None:
    """Without --log-dir a child's output used to go to /dev/null: "exited with code 1" only."""
    proc = metricslam("up", "--no-scale", "--zenoh-endpoint", f"tcp/127.0.0.1:{free_port()}",
                      env={"SLAM_MAX_CAMERAS": "-1"}, timeout=120)
    line = error_line(proc, "up", "slam-service exited with code 1 while starting")
    assert line.endswith("its last output:"), line
    tail = proc.stderr[proc.stderr.index(line):].splitlines()[1:]
    assert any("slam-service| metricslam slam-service: error:" in t and "SLAM_MAX_CAMERAS" in t
               for t in tail), proc.stderr


def test_a_child_keeps_only_the_tail_of_its_output() -> None:
    code = "import sys\nfor i in range(5000): print('line', i)\nprint('the reason', file=sys.stderr)\nsys.exit(3)"
    child = Child("talker", [sys.executable, "-c", code], lambda: False, "nowhere")
    child.start()
    child.process.wait(60)
    tail = child.output_tail()
    assert tail[-1] == "the reason" and tail[-2] == "line 4999" and len(tail) <= 20
    message = child.failure(" while starting")
    assert message.startswith("talker exited with code 3 while starting; its last output:\n")
    assert message.splitlines()[-1] == "  talker| the reason"
