"""Clients of a running SLAM service over Zenoh: publish frames, record poses, query it.

Used by ``metricslam replay`` / ``poses`` / ``camera``, the supervisor's readiness probe, the
demo, the benchmarks and the tests. Speaks only the wire format (``metricslam.wire``); imports
nothing from ``service``.
"""
