"""Test helper: the real SLAM pipeline over a whole sequence folder, deterministically."""

from __future__ import annotations

from pathlib import Path


def run_inline(seq_dir: Path, use_scale: bool, preset: str = "synth"):
    """Run :class:`SlamPipeline` with the global back end inline (same thread, deterministic)
    over every frame of ``seq_dir``; returns the closed ``(pipeline, backend)``."""
    from metricslam.datasets import open_sequence
    from metricslam.slam.backend_factory import make_backend
    from metricslam.slam.graph.config import GraphConfig
    from metricslam.slam.pipeline import SlamPipeline
    from metricslam.slam.vo.config import VOConfig

    seq = open_sequence(seq_dir)
    backend = make_backend(seq.camera, use_scale=use_scale, config=GraphConfig(inline=True))
    pipe = SlamPipeline(seq.camera, VOConfig.preset(preset), backend=backend)
    try:
        for i in range(len(seq)):
            pipe.process(seq[i])
    finally:
        pipe.close()
    return pipe, backend
