"""The SLAM service over Zenoh and what runs around it, as four subpackages and two modules.

Layers, top to bottom (an import only points down; ``lint-imports`` checks it, pyproject.toml):

* ``demo`` — ``metricslam demo``: a synthetic loop through the supervised stack, scored.
* ``supervisor/`` — the local stack as child processes: ``launcher`` (``metricslam up``),
  ``router`` (a zenoh router in Python), ``child`` (a child that dies with its parent),
  ``healthcheck`` (the container readiness probe).
* ``service/`` — the service itself: ``slam_service`` (subscriptions, publications,
  queryables), ``settings`` (env ``SLAM_*``), ``camera_worker`` (per-camera bounded queue and
  session), ``sessions`` (session factory), ``map_publisher``, ``http_depth`` (depth service
  client), ``ros2_bridge``.
* ``tools/`` — clients of a running service, independent of ``service/``: ``client`` (frame
  publisher, pose recorder, trajectory and health queries), ``replay``, ``recording``.
* ``zenoh_config`` — session configuration shared by all of the above.

See docs/architecture.md and docs/deployment.md.
"""
