"""``build_session``: the one way to assemble a running SLAM system from a :class:`SystemConfig`.

Used by ``metricslam run``, the SLAM service (one session per camera), the benchmarks and the
tests, so they cannot drift apart. The session is a :class:`~metricslam.slam.pipeline.SlamPipeline`
(local VO + optional global Sim(3) back end with loop closure and learned scale factors) whose
:class:`~metricslam.slam.scale_history.ScaleHistory` records the scale estimate over time from the
back end's events (``session.backend.events``, :mod:`metricslam.slam.events`).

Example::

    config = load_system_config("my.yaml")                 # defaults → file → METRICSLAM_* env
    session = build_session(seq.camera, config, default_preset=preset_for(seq_dir))
    for i in range(len(seq)):
        session.process(seq[i])
    session.close()
"""

from __future__ import annotations

import logging
from pathlib import Path

from metricslam.camera import PinholeCamera
from metricslam.slam.backend_factory import make_backend
from metricslam.slam.depth_source import DepthSource, OnnxDepthSource
from metricslam.slam.ground.meter import GroundScaleMeter
from metricslam.slam.pipeline import SlamPipeline
from metricslam.slam.scale_history import ScaleHistory
from metricslam.slam.system_config import DEFAULT_PRESET, SystemConfig

log = logging.getLogger(__name__)

#: VO preset per dataset format (:func:`metricslam.datasets.detect_format`)
_PRESET_BY_FORMAT = {"kitti": "kitti", "kitti_raw_depth": "kitti", "euroc": "euroc", "tum": "tum"}


def build_session(camera: PinholeCamera, config: SystemConfig,
                  depth_source: DepthSource | None = None,
                  default_preset: str = DEFAULT_PRESET) -> SlamPipeline:
    """A ready :class:`SlamPipeline` for frames of ``camera``.

    Args:
        camera: intrinsics of the incoming frames.
        config: the whole system's configuration (:mod:`metricslam.slam.system_config`).
        depth_source: metric inverse depth for learned scale factors (e.g. the SLAM service's
            HTTP client, a stereo reference in a benchmark); None: the in-process ONNX model
            ``config.depth.model_path``. Not called when ``config.use_scale`` is False.
        default_preset: VO preset when ``config.vo.preset`` is None.

    Returns:
        The session; ``session.backend`` is None in ``vo_only`` mode.
    """
    vo_config = config.vo_config(default_preset)
    graph_config = config.graph_config()
    history = ScaleHistory()
    backend = None
    if not config.vo_only:
        source = None
        if config.use_scale:
            source = depth_source if depth_source is not None else OnnxDepthSource(config.depth.model_path)
        ground = GroundScaleMeter(config.scale) if config.use_ground else None
        backend = make_backend(camera, use_scale=config.use_scale, depth_source=source,
                               config=graph_config, ground_meter=ground)
        if source is not None:
            history.attach(backend.events)
    log.debug("built a %s session: VO %s", config.mode, vo_config.model_dump())
    pipeline = SlamPipeline(camera, vo_config, backend=backend, scale_history=history,
                            initial_scale=config.initial_scale if config.use_scale else None)
    if backend is not None and graph_config.loop.enabled and graph_config.loop.relocalize_segments:
        from metricslam.slam.map.segments import SegmentRelocalizer

        SegmentRelocalizer(camera, graph_config.loop, vo_config.coast_max_s).attach(pipeline)
    pipeline.scale_info = {"sources": [s for s, on in (("learned", config.use_scale), ("ground", config.use_ground))
                                       if on], "mount_height_m": config.scale.mount_height_m}
    return pipeline


def preset_for(seq_dir: str | Path) -> str:
    """The VO preset for a sequence folder: ``synth`` for ``metricslam synth`` output, else by
    dataset format (:data:`_PRESET_BY_FORMAT`), ``kitti`` for anything else.

    A render is recognised by its ground truth *inside* the folder (``depth_0/`` and
    ``poses/``, as :class:`metricslam.synth.writer.KittiWriter` writes them). ``depth_0/`` alone is
    not enough: KITTI raw drives keep projected LiDAR there (``kitti_raw_stereo``) and their
    poses beside ``sequences/``; they are real KITTI footage and get the ``kitti`` preset.
    """
    from metricslam.datasets import detect_format

    root = Path(seq_dir)
    if (root / "depth_0").is_dir() and (root / "poses").is_dir():
        return "synth"
    return _PRESET_BY_FORMAT.get(detect_format(seq_dir), DEFAULT_PRESET)
