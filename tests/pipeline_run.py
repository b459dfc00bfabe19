"""Test helper: the real SLAM system over a whole sequence folder, deterministically."""

from __future__ import annotations

from pathlib import Path


def run_inline(seq_dir: Path, use_scale: bool, preset: str = "synth", depth_source=None):
    """Run the session :func:`~metricslam.slam.session_builder.build_session` makes from a
    deterministic :class:`~metricslam.slam.system_config.SystemConfig` (BA, depth and the global
    solve in the frame loop: ``metricslam run --deterministic``) over every frame of ``seq_dir``.

    Returns:
        the closed ``(pipeline, backend)``.
    """
    from metricslam.datasets import open_sequence
    from metricslam.slam.session_builder import build_session
    from metricslam.slam.system_config import SystemConfig

    seq = open_sequence(seq_dir)
    config = SystemConfig(vo={"preset": preset}, depth={"use_scale": use_scale}, deterministic=True)
    pipe = build_session(seq.camera, config, depth_source=depth_source)
    try:
        for i in range(len(seq)):
            pipe.process(seq[i])
    finally:
        pipe.close()
    return pipe, pipe.backend
