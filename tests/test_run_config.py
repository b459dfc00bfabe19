"""``metricslam run --config FILE.yaml``: VO and graph overrides, validated before any frame."""

from __future__ import annotations

import json

import pytest
from metricslam.cli.main import main
from metricslam.errors import ConfigError
from metricslam.slam.config_file import load_overrides
from metricslam.slam.graph.config import GraphConfig
from metricslam.slam.vo.config import VOConfig


def _write(tmp_path, text: str):
    path = tmp_path / "config.yaml"
    path.write_text(text)
    return path


def test_no_file_means_defaults_and_presets() -> None:
    o = load_overrides(None)
    assert o.graph_config() == GraphConfig()
    assert o.vo_config("kitti") == VOConfig.preset("kitti")


def test_overrides_reach_both_configs_and_the_command_line_wins(tmp_path) -> None:
    path = _write(tmp_path, "vo:\n  keyframe_motion_px: 31\ngraph:\n  odom_sigma_log_scale: 0.01\n"
                            "  depth_queue_size: 3\n  loop:\n    vocabulary_words: 1000\n")
    o = load_overrides(path)
    g = o.graph_config(depth_queue_size=256)
    assert g.odom_sigma_log_scale == 0.01 and g.loop.vocabulary_words == 1000
    assert g.depth_queue_size == 256  # the command line's value wins over the file
    assert g.scale_sigma_floor_log == GraphConfig().scale_sigma_floor_log  # untouched default
    vo = o.vo_config("synth")
    assert vo.keyframe_motion_px == 31
    assert vo.max_features == VOConfig.preset("synth").max_features  # the preset's other values


@pytest.mark.parametrize("text, needle", [
    ("graph:\n  odom_sigma_log_scal: 0.01\n", "odom_sigma_log_scal"),       # misspelled key
    ("graph:\n  odom_sigma_log_scale: -1\n", "odom_sigma_log_scale"),      # out of range
    ("graph:\n  loop:\n    vocabulary_wrds: 9\n", "vocabulary_wrds"),       # nested typo
    ("vo:\n  keyframe_motion_px: fast\n", "keyframe_motion_px"),           # wrong type
    ("frontend:\n  x: 1\n", "sections"),                                    # unknown section
    ("graph: [1, 2]\n", "mapping"),                                         # not a mapping
    ("graph: {odom: [\n", "not valid YAML"),                                # broken YAML
])
def test_bad_files_are_refused_naming_the_problem(tmp_path, text, needle) -> None:
    with pytest.raises(ConfigError, match=needle):
        load_overrides(_write(tmp_path, text))


def test_missing_file_is_refused(tmp_path) -> None:
    with pytest.raises(ConfigError, match="does not exist"):
        load_overrides(tmp_path / "nope.yaml")


def test_run_refuses_a_bad_config_before_reading_the_sequence(tmp_path, capsys) -> None:
    out = tmp_path / "est.txt"
    rc = main(["run", str(tmp_path / "no_such_sequence"), "--out", str(out), "--no-progress",
               "--config", str(_write(tmp_path, "graph:\n  odom_sigma: 1\n"))])
    assert rc == 1 and not out.exists()
    assert "odom_sigma" in capsys.readouterr().err


@pytest.mark.slow
def test_run_applies_the_vo_overrides(shared_data, tmp_path) -> None:
    """A config that makes every frame a keyframe changes the real run's keyframe count."""
    seq = shared_data / "kitti_odometry" / "sequences" / "06"

    def keyframes(extra: list[str]) -> int:
        stats = tmp_path / "stats.json"
        assert main(["run", str(seq), "--out", str(tmp_path / "est.txt"), "--json", str(stats), "--vo-only",
                     "--max-frames", "20", "--no-progress", *extra]) == 0
        return json.loads(stats.read_text())["keyframes"]

    path = _write(tmp_path, "vo:\n  keyframe_max_frames: 1\n  keyframe_motion_px: 1.0\n")
    default, every_frame = keyframes([]), keyframes(["--config", str(path)])
    assert every_frame > default + 5, (default, every_frame)


@pytest.mark.slow
def test_deterministic_runs_give_the_same_trajectory_byte_for_byte(synth_sequence, tmp_path) -> None:
    """``--deterministic``: BA, depth and the global solve in the frame loop; metric mode."""
    seq = synth_sequence(60)
    outs = []
    for k in range(2):
        out, stats = tmp_path / f"est{k}.txt", tmp_path / f"stats{k}.json"
        assert main(["run", str(seq), "--out", str(out), "--json", str(stats), "--deterministic",
                     "--no-progress"]) == 0
        outs.append(out.read_bytes())
        info = json.loads(stats.read_text())
        assert info["deterministic"] is True and info["mode"] == "metric"
        assert info["backend"]["scale_factors"] > 0  # the learned scale really took part
    assert outs[0] == outs[1] and len(outs[0].splitlines()) == 60
