"""Where the mounting height comes from (issue #33): ``scale.sources: [ground]`` needs a height,
but the height may sit in another layer than the sources — the calibration file's
``mount_height_m``, the environment, a config file or the command line — so the rule is checked on
the combined configuration, not per layer. A bad height in any of them is one clear error line
before anything starts."""

from __future__ import annotations

import pytest

from metricslam.errors import ConfigError
from metricslam.slam.config_file import load_system_config
from metricslam_cli.main import build_parser, main
from metricslam_cli.run_cmd import config_from_args

BAD_HEIGHTS = ["0", "-1.65", "10.5", "nan", "inf"]


def _calib(tmp_path, mount: str = "") -> str:
    p = tmp_path / "cam.yaml"
    p.write_text("width: 640\nheight: 480\nfx: 500\nfy: 500\ncx: 319.5\ncy: 239.5\n"
                 + (f"mount_height_m: {mount}\n" if mount else ""))
    return str(p)


def _run_config(argv: list[str]):
    return config_from_args(build_parser().parse_args(["run", "SEQ", "--out", "est.txt", *argv]))


@pytest.fixture(autouse=True)
def _no_outside_config(monkeypatch):
    for name in ("METRICSLAM_CONFIG", "METRICSLAM_SCALE__SOURCES", "METRICSLAM_SCALE__MOUNT_HEIGHT_M"):
        monkeypatch.delenv(name, raising=False)


def test_calibration_height_serves_ground_sources_from_the_command_line(tmp_path):
    config = _run_config(["--calib", _calib(tmp_path, "1.2"), "--scale-sources", "ground"])
    assert config.scale.sources == ("ground",) and config.scale.mount_height_m == 1.2 and config.use_ground
    # --mount-height beats the calibration file
    config = _run_config(["--calib", _calib(tmp_path, "1.2"), "--scale-sources", "learned,ground",
                          "--mount-height", "1.5"])
    assert config.scale.mount_height_m == 1.5


def test_calibration_height_serves_ground_sources_from_the_environment_or_a_config_file(tmp_path, monkeypatch):
    monkeypatch.setenv("METRICSLAM_SCALE__SOURCES", '["ground"]')
    assert _run_config(["--calib", _calib(tmp_path, "1.3")]).scale.mount_height_m == 1.3
    monkeypatch.delenv("METRICSLAM_SCALE__SOURCES")
    cfg_file = tmp_path / "ground.yaml"
    cfg_file.write_text("scale:\n  sources: [learned, ground]\n")
    config = _run_config(["--config", str(cfg_file), "--calib", _calib(tmp_path, "1.3")])
    assert config.scale.sources == ("learned", "ground") and config.scale.mount_height_m == 1.3


def test_a_height_in_the_environment_serves_ground_sources_from_the_command_line(monkeypatch):
    monkeypatch.setenv("METRICSLAM_SCALE__MOUNT_HEIGHT_M", "1.65")
    config = _run_config(["--scale-sources", "ground"])
    assert config.scale.sources == ("ground",) and config.scale.mount_height_m == 1.65


def test_ground_without_a_height_anywhere_is_one_clear_error(tmp_path):
    with pytest.raises(ConfigError, match=r"combined configuration: .*'ground' needs the camera's mounting "
                                          r"height: give --mount-height M, mount_height_m in the calibration"):
        _run_config(["--calib", _calib(tmp_path), "--scale-sources", "ground"])
    with pytest.raises(ConfigError, match="needs the camera's mounting height"):
        load_system_config(env={"METRICSLAM_SCALE__SOURCES": "[ground]"})


@pytest.mark.parametrize("h", BAD_HEIGHTS)
def test_a_bad_height_from_any_source_is_one_line_and_nothing_starts(h, tmp_path, monkeypatch, capsys):
    def started(*a, **k):
        raise AssertionError("something started")

    monkeypatch.setattr("metricslam.slam.depth_source.OnnxDepthSource.load", started)
    monkeypatch.setattr("metricslam.datasets.open_sequence", started)
    seq = str(tmp_path / "seq")
    runs = [["--mount-height", h, "--scale-sources", "ground"],
            ["--calib", _calib(tmp_path, ".nan" if h == "nan" else ".inf" if h == "inf" else h)]]
    for argv in runs:
        assert main(["run", seq, "--out", str(tmp_path / "e.txt"), "--no-progress", *argv]) == 1
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and "metres" in err and "0 < h <= 10" in err, err
    monkeypatch.setenv("METRICSLAM_SCALE__MOUNT_HEIGHT_M", h)
    assert main(["run", seq, "--out", str(tmp_path / "e.txt"), "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "environment (METRICSLAM_*)" in err and "scale.mount_height_m" in err, err
    assert err.count("scale.mount_height_m") == 1  # named once
