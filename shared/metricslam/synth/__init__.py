"""Synthetic KITTI-like stereo driving sequences with exact metric depth and poses.

``generate_sequence(out_dir, frames, seed, ...)`` writes the KITTI odometry layout plus
``depth_0/`` (uint16, metres × 256); :class:`SynthScene` renders frames in memory.
See ``docs/synth.md``.
"""

from metricslam.synth.scene import (
    StereoFrame,
    SynthConfig,
    SynthScene,
    generate_sequence,
    kitti_like_camera,
)

__all__ = ["StereoFrame", "SynthConfig", "SynthScene", "generate_sequence", "kitti_like_camera"]
