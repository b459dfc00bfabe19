"""``SystemConfig`` loading (defaults → YAML → ``METRICSLAM_*`` → flags) and ``metricslam run
--config FILE.yaml``: overrides validated before any frame."""

from __future__ import annotations

import json
import os

import pytest
from metricslam.errors import ConfigError
from metricslam.slam.config_file import load_system_config
from metricslam.slam.graph.config import GraphConfig
from metricslam.slam.system_config import SystemConfig
from metricslam.slam.vo.config import VOConfig
from metricslam_cli.main import main
from pydantic import ValidationError

NO_ENV: dict[str, str] = {}


def _write(tmp_path, text: str):
    path = tmp_path / "config.yaml"
    path.write_text(text)
    return path


def test_no_file_means_defaults_and_presets() -> None:
    c = load_system_config(None, env=NO_ENV)
    assert c == SystemConfig()
    assert c.graph_config() == GraphConfig()
    assert c.vo_config("kitti") == VOConfig.preset("kitti")
    assert c.use_scale and c.mode == "metric" and not c.deterministic


def test_overrides_reach_both_configs_and_the_command_line_wins(tmp_path) -> None:
    path = _write(tmp_path, "vo:\n  keyframe_motion_px: 31\ngraph:\n  odom_sigma_log_scale: 0.01\n"
                            "  depth_queue_size: 3\n  loop:\n    vocabulary_words: 1000\n")
    c = load_system_config(path, env=NO_ENV, overrides={"graph": {"depth_queue_size": 256}})
    g = c.graph_config()
    assert g.odom_sigma_log_scale == 0.01 and g.loop.vocabulary_words == 1000
    assert g.depth_queue_size == 256  # the command line's value wins over the file
    assert g.scale_sigma_floor_log == GraphConfig().scale_sigma_floor_log  # untouched default
    assert g.loop.n_candidates == GraphConfig().loop.n_candidates  # nested default kept
    vo = c.vo_config("synth")
    assert vo.keyframe_motion_px == 31
    assert vo.max_features == VOConfig.preset("synth").max_features  # the preset's other values


def test_layers_apply_in_order_defaults_profile_file_environment_flags(tmp_path) -> None:
    path = _write(tmp_path, "graph:\n  depth_queue_size: 3\n  odom_sigma_log_scale: 0.01\n"
                            "vo:\n  preset: euroc\n")
    env = {"METRICSLAM_GRAPH__ODOM_SIGMA_LOG_SCALE": "0.02", "METRICSLAM_GRAPH__LOOP__ENABLED": "false",
           "METRICSLAM_DETERMINISTIC": "1", "METRICSLAM_SHARED_DATA": "/elsewhere"}  # not ours
    profile = {"graph": {"depth_queue_size": 256, "relinearize_skip": 5}}
    c = load_system_config(path, env=env, profile=profile, overrides={"vo": {"preset": "tum"}})
    assert c.graph.relinearize_skip == 5           # profile over the class default
    assert c.graph.depth_queue_size == 3           # file over the profile
    assert c.graph.odom_sigma_log_scale == 0.02    # environment over the file
    assert c.graph.loop.enabled is False and c.deterministic
    assert c.vo.preset == "tum"                    # flags over everything
    assert c.vo_config().ba_in_background is False and c.graph_config().inline is True


def test_config_file_from_the_environment(tmp_path) -> None:
    path = _write(tmp_path, "depth:\n  use_scale: false\nqueues:\n  frames: 3\nvo_only: true\n")
    c = load_system_config(None, env={"METRICSLAM_CONFIG": str(path)})
    assert not c.depth.use_scale and c.queues.frames == 3 and c.mode == "vo-only" and not c.use_scale
    with pytest.raises(ConfigError, match="does not exist"):
        load_system_config(None, env={"METRICSLAM_CONFIG": str(tmp_path / "nope.yaml")})


def test_deterministic_mode_wins_over_the_file(tmp_path) -> None:
    path = _write(tmp_path, "vo:\n  ba_in_background: true\ngraph:\n  inline: false\n")
    c = load_system_config(path, env=NO_ENV, overrides={"deterministic": True})
    assert c.vo_config("kitti").ba_in_background is False and c.graph_config().inline is True
    assert c.graph.inline is False  # the file's value is kept; the mode fixes the resolved one


@pytest.mark.parametrize("env, needle", [
    ({"METRICSLAM_GRPAH__ODOM_SIGMA_LOG_SCALE": "1"}, "grpah"),           # misspelled section
    ({"METRICSLAM_GRAPH__ODOM_SIGMA": "1"}, "odom_sigma"),                # stale key
    ({"METRICSLAM_GRAPH__ODOM_SIGMA_LOG_SCALE": "-1"}, "odom_sigma_log_scale"),
    ({"METRICSLAM_VO__KEYFRAME_MOTION_PX": "fast"}, "keyframe_motion_px"),
    ({"METRICSLAM_VO__PRESET": "mars"}, "preset"),
    ({"METRICSLAM_GRAPH": "1"}, "METRICSLAM_GRAPH"),                      # section without a field
])
def test_bad_environment_is_refused_naming_the_variable(env, needle) -> None:
    with pytest.raises(ConfigError, match=needle) as info:
        load_system_config(None, env=env)
    assert "environment" in str(info.value)


@pytest.mark.parametrize("text, needle", [
    ("graph:\n  odom_sigma_log_scal: 0.01\n", "odom_sigma_log_scal"),       # misspelled key
    ("graph:\n  odom_sigma_log_scale: -1\n", "odom_sigma_log_scale"),      # out of range
    ("graph:\n  loop:\n    vocabulary_wrds: 9\n", "vocabulary_wrds"),       # nested typo
    ("vo:\n  keyframe_motion_px: fast\n", "keyframe_motion_px"),           # wrong type
    ("vo:\n  preset: mars\n", "preset"),                                    # unknown preset
    ("depth:\n  model: x.onnx\n", "model"),                                 # stale depth key
    ("frontend:\n  x: 1\n", "sections"),                                    # unknown section
    ("graph: [1, 2]\n", "mapping"),                                         # not a mapping
    ("graph: {odom: [\n", "not valid YAML"),                                # broken YAML
])
def test_bad_files_are_refused_naming_the_problem(tmp_path, text, needle) -> None:
    path = _write(tmp_path, text)
    with pytest.raises(ConfigError, match=needle) as info:
        load_system_config(path, env=NO_ENV)
    assert str(path) in str(info.value)


def test_missing_file_is_refused(tmp_path) -> None:
    with pytest.raises(ConfigError, match="does not exist"):
        load_system_config(tmp_path / "nope.yaml", env=NO_ENV)


def test_system_config_is_frozen_and_strict() -> None:
    c = SystemConfig()
    with pytest.raises(ValidationError, match="frozen"):
        c.deterministic = True  # type: ignore[misc]
    with pytest.raises(ValidationError, match="graphs"):
        SystemConfig(graphs={})


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


def test_slam_service_takes_the_same_file_as_run(tmp_path, monkeypatch) -> None:
    """``metricslam slam-service --config`` / ``METRICSLAM_CONFIG`` load what ``run`` loads; only
    ``run``'s offline depth queue differs."""
    from metricslam_cli import run_cmd, slam_service_cmd
    from metricslam_cli.main import build_parser

    for name in [n for n in os.environ if n.startswith("METRICSLAM_")]:
        monkeypatch.delenv(name)
    path = _write(tmp_path, "vo:\n  preset: euroc\n  keyframe_motion_px: 31\ngraph:\n  loop:\n    enabled: false\n")
    parser = build_parser()
    live = slam_service_cmd.config_from_args(parser.parse_args(["slam-service", "--config", str(path)]))
    offline = run_cmd.config_from_args(parser.parse_args(["run", "SEQ", "--out", "x", "--config", str(path)]))
    assert live.vo == offline.vo and live.vo.preset == "euroc" and live.graph.loop.enabled is False
    assert live.graph.model_copy(update={"depth_queue_size": 256}) == offline.graph
    # the live service starts metric (initial scale); offline runs stay as they were
    assert live.initial_scale.enabled and not offline.initial_scale.enabled
    monkeypatch.setenv("METRICSLAM_CONFIG", str(path))
    from_env = slam_service_cmd.config_from_args(parser.parse_args(["slam-service", "--queue-size", "3"]))
    assert from_env.vo == live.vo and from_env.queues.frames == 3


def test_slam_service_refuses_a_bad_config_before_connecting(tmp_path, capsys) -> None:
    rc = main(["slam-service", "--zenoh-endpoint", "tcp/127.0.0.1:17487",
               "--config", str(_write(tmp_path, "graph:\n  odom_sigma: 1\n"))])
    assert rc == 1 and "odom_sigma" in capsys.readouterr().err
