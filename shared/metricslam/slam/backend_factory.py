"""Build the global back end the pipeline and ``metricslam run`` use."""

from __future__ import annotations

from pathlib import Path

from metricslam.camera import PinholeCamera
from metricslam.slam.depth_source import DepthSource, OnnxDepthSource
from metricslam.slam.graph.backend import GlobalBackend
from metricslam.slam.graph.config import GraphConfig
from metricslam.slam.ground.meter import GroundScaleMeter
from metricslam.slam.loop.detector import LoopDetector


def make_backend(camera: PinholeCamera, use_scale: bool, model_path: str | Path | None = None,
                 depth_source: DepthSource | None = None,
                 config: GraphConfig | None = None,
                 ground_meter: GroundScaleMeter | None = None) -> GlobalBackend:
    """A :class:`GlobalBackend` with loop closure and (optionally) learned scale factors.

    Args:
        camera: intrinsics of the keyframe images (kept for API symmetry; each keyframe carries
            its own camera).
        use_scale: add learned scale factors. ``False`` is the ``--no-scale`` ablation: the same
            graph and loops, no depth source is created or called, the first keyframe's scale
            is anchored (output in VO units).
        model_path: ONNX model for the in-process depth source (None: the shipped model).
        depth_source: use this source instead (e.g. the HTTP depth service client).
        config: graph parameters (default :class:`GraphConfig`).
        ground_meter: ground-plane scale factors from this meter (None: none).
    """
    del camera
    config = config or GraphConfig()
    source = None
    if use_scale:
        source = depth_source if depth_source is not None else OnnxDepthSource(model_path)
    detector = LoopDetector(config.loop) if config.loop.enabled else None
    return GlobalBackend(config, depth_source=source, loop_detector=detector, ground_meter=ground_meter)
