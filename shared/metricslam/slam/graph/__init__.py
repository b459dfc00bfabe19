"""Global Sim(3) pose graph with learned scale factors (paper §III-D).

Modules: :mod:`config` (``GraphConfig``), :mod:`gtsam_sim3` (4x4 <-> ``gtsam.Similarity3``),
:mod:`odometry` (relative Sim(3) between keyframes across VO corrections), :mod:`scale_factor`
(eq. 12 as C++ gtsam priors on log-scale), :mod:`sim3_graph` (``GlobalPoseGraph``, ISAM2) and
:mod:`backend` (``GlobalBackend``, the threaded orchestrator). See ``docs/global_graph.md``.
"""

from metricslam.slam.graph.config import GraphConfig, LoopConfig

__all__ = ["GraphConfig", "LoopConfig"]
