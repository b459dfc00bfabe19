"""The SLAM service: Zenoh adapter over the pure ``metricslam`` SLAM core.

Modules: ``settings`` (env ``SLAM_*``), ``service`` (subscriptions, publications, queryables),
``camera_worker`` (per-camera bounded queue + session), ``sessions`` (session factory),
``http_depth`` (depth service client), ``router`` (local zenoh router), ``launcher`` (``up``).
"""
