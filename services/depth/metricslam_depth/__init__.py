"""metricslam depth service: the depth network behind a FastAPI + onnxruntime HTTP API.

Entry points: ``metricslam depth-service`` (CLI), ``python -m metricslam_depth``,
:func:`metricslam_depth.app.create_app` (ASGI app), :class:`metricslam_depth.process.ServiceProcess`
(a child-process instance for tests and benchmarks). See ``docs/depth_service.md``.
"""
