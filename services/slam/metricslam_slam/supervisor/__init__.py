"""The local stack as supervised child processes (``metricslam up``) and its probes.

``launcher`` starts a zenoh ``router``, the depth service and the SLAM service (the ``metricslam``
commands, in child processes started through ``child``), waits until each is ready and restarts
those that die; ``healthcheck`` is the SLAM container's readiness probe.
"""
