"""metricslam — metrically-scaled monocular SLAM with learned scale factors.

The core library (this package) is pure numpy/OpenCV/gtsam/onnxruntime: it never imports
zenoh, FastAPI, httpx or torch. Services (``metricslam_depth``, ``metricslam_slam``),
training (``metricslam_train``) and the command line (``metricslam_cli``) are separate packages
on top of it (docs/architecture.md).

Conventions (frames, ``T_a_b``, tangent orders): ``docs/conventions.md``.
"""

from metricslam.errors import MetricSlamError

__all__ = ["MetricSlamError", "__version__"]
__version__ = "0.1.0"
