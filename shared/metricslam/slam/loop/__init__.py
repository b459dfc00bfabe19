"""Loop closure: ORB bag-of-words place recognition, geometric verification, relative Sim(3).

:mod:`vocabulary` (binary visual words + TF-IDF database), :mod:`verification` (landmark
descriptor matching + RANSAC Umeyama Sim(3) with a two-way reprojection test) and
:mod:`detector` (``LoopDetector``, what the global back end calls).
"""

from metricslam.slam.loop.detector import LoopCandidate, LoopDetector

__all__ = ["LoopCandidate", "LoopDetector"]
