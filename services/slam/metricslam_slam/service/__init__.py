"""The SLAM service: a Zenoh adapter over the pure ``metricslam`` SLAM core, one session per camera.

Entry point: ``metricslam slam-service`` (:class:`.slam_service.SlamService` with
:class:`.settings.SlamServiceSettings`). Imports nothing from ``tools``, ``supervisor`` or ``demo``.
"""
