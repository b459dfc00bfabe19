"""The command line is consistent (issue #35): every option of every command has a help line
and shows its default; ``--version``; ``run --help`` names TUM; ``poses`` records until Ctrl-C;
``depth --out DIR`` writes inside DIR. (``quantize --calib-images``: tests/test_depth_quantize.py.)
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import metricslam
from metricslam_cli.main import build_parser, main, shows_default

CLI = [sys.executable, "-m", "metricslam_cli.main"]
#: options still without a help line in files this change could not edit (the scale-health work
#: owns camera_cmd.py); strict: the test fails once they have one, so this list shrinks to nothing
KNOWN_WITHOUT_HELP = {("camera", "--zenoh-endpoint"), ("camera", "--camera-id")}


def _commands() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(sub.choices)


def _options(name: str, parser: argparse.ArgumentParser):
    for action in parser._actions:
        if isinstance(action, (argparse._HelpAction, argparse._VersionAction)):
            continue
        yield (action.option_strings[0] if action.option_strings else action.dest), action


def _rendered(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    formatter = parser._get_formatter()
    return formatter._expand_help(action) if action.help else ""


@pytest.mark.parametrize("command", sorted(_commands()))
def test_every_option_has_help_and_shows_its_default(command: str) -> None:
    parser = _commands()[command]
    problems = []
    for name, action in _options(command, parser):
        if (command, name) in KNOWN_WITHOUT_HELP:
            assert not action.help, f"{command} {name} has help now: drop it from KNOWN_WITHOUT_HELP"
            continue
        if not action.help or action.help == argparse.SUPPRESS:
            problems.append(f"{name}: no help")
            continue
        text = _rendered(parser, action)
        if shows_default(action) and "default" not in text.lower():
            problems.append(f"{name}: default {action.default!r} not shown in {text!r}")
    assert not problems, f"metricslam {command}: " + "; ".join(problems)
    assert "usage: metricslam " + command in parser.format_help()


def test_defaults_are_rendered_with_their_value() -> None:
    replay = _commands()["replay"]
    text = " ".join(replay.format_help().split())
    assert "(default: 10.0)" in text and "(default: cam0)" in text  # --rate, --camera-id


def test_version_prints_the_package_version(capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"metricslam {metricslam.__version__}"


def test_run_help_names_tum() -> None:
    out = subprocess.run(CLI + ["run", "--help"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0
    assert "TUM RGB-D" in out.stdout and "--format" in out.stdout and "tum" in out.stdout


def test_poses_records_until_ctrl_c(tmp_path: Path) -> None:
    """No --frames: records until SIGINT, then writes frames 0..last (missing ones reported, not
    an error) and exits 0."""
    from metricslam.slam.types import ScaleState, TrackingState
    from metricslam.wire import keys
    from metricslam.wire.codec import PoseMessage, encode
    from metricslam_slam.supervisor.router import open_router
    from metricslam_slam.zenoh_config import open_client

    from metricslam_slam.supervisor.launcher import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(endpoint)
    client = open_client(endpoint)
    out = tmp_path / "est.tum"
    proc = subprocess.Popen(CLI + ["poses", "--zenoh-endpoint", endpoint, "--out", str(out), "--format", "tum"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert "Ctrl-C" in proc.stdout.readline()
        publisher = client.declare_publisher(keys.key("cam0", "pose"))
        deadline = time.monotonic() + 30  # until zenoh knows the recorder's subscription (slow when loaded)
        while not publisher.matching_status.matching:
            assert time.monotonic() < deadline, "the poses recorder never subscribed"
            time.sleep(0.01)
        for i in (1, 2, 3):
            T = np.eye(4)
            T[0, 3] = float(i)
            publisher.put(encode(PoseMessage(
                camera_id="cam0", frame_index=i, t_ns=i * 10**8, state=TrackingState.TRACKING,
                scale_established=True, scale_state=ScaleState.METRIC, T_world_cam=T)))
        time.sleep(2.0)  # delivery to the recorder (loopback; slow when loaded)
        assert proc.poll() is None, proc.stdout.read()  # still recording: no --frames to reach
        publisher.undeclare()
        proc.send_signal(signal.SIGINT)
        printed, _ = proc.communicate(timeout=90)  # it writes and closes promptly; generous when loaded
        assert proc.returncode == 0, printed
    finally:
        if proc.poll() is None:
            proc.kill()
        client.close()
        router.close()
    assert "stopped (Ctrl-C)" in printed and "wrote 3 poses" in printed
    assert "1 of frames 0-3 have no pose" in printed
    lines = [line for line in out.read_text().splitlines() if not line.startswith("#")]
    assert [float(line.split()[1]) for line in lines] == [1.0, 2.0, 3.0]


def test_depth_out_folder_is_written_inside(tmp_path: Path) -> None:
    import cv2

    from metricslam_cli.depth_cmd import out_path

    folder = tmp_path / "maps"
    folder.mkdir()
    assert out_path(str(folder), "x/frame7.png") == folder / "frame7.depth.npy"
    assert out_path(str(tmp_path / "new") + "/", "frame7.png") == tmp_path / "new" / "frame7.depth.npy"
    assert out_path(str(tmp_path / "d.npy"), "frame7.png") == tmp_path / "d.npy"
    image = tmp_path / "frame7.png"
    y, x = np.mgrid[0:64, 0:128]
    cv2.imwrite(str(image), (x * 2 + y).astype(np.uint8))
    assert main(["depth", str(image), "--fx", "100", "--out", str(folder)]) == 0
    depth = np.load(folder / "frame7.depth.npy")
    assert depth.ndim == 2 and not (folder / ".npy").exists()
