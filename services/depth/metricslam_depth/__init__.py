"""metricslam depth service: the depth network behind a FastAPI + onnxruntime HTTP API.

Entry points: ``metricslam depth-service`` (CLI), ``python -m metricslam_depth``,
:func:`metricslam_depth.app.create_app` (ASGI app). Tests and benchmarks start it as a child
process with ``tests/depth_service_process.py``. See ``docs/depth_service.md``.
"""
