# Depth inference service: FastAPI + onnxruntime + the shipped ONNX models.
# Installs the core's base dependencies and the depth-service extra (pyproject.toml): no torch, no
# zenoh, no renderer (numba, scikit-image); gtsam comes with the core's base set.
# Serves the int8 depth_l3_int8.onnx by default; the float32 depth_l3.onnx is installed next to it
# (DEPTH_MODEL_PATH=/usr/local/lib/python3.11/site-packages/metricslam/models/depth_l3.onnx).
# Build from the repository root:  docker build -f deploy/depth.Dockerfile -t metricslam-depth:0.1.0 .
# (tag with the project's version, pyproject.toml; docker-compose.yml and deploy/k8s use it)
# BASE_IMAGE: any image with Python 3.11 whose `python` and `pip` are on PATH (deploy/images_smoke.py
# builds with one made from Debian packages, where registry images are out of reach)
ARG BASE_IMAGE=python:3.11-slim
FROM ${BASE_IMAGE}

ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /app

COPY pyproject.toml README.md ./
COPY shared/ shared/
COPY cli/ cli/
COPY services/ services/
COPY training/metricslam_train/__init__.py training/metricslam_train/__init__.py
RUN pip install ".[depth-service]" && useradd --system --uid 10001 metricslam

USER metricslam
ENV DEPTH_HOST=0.0.0.0 DEPTH_PORT=8100 DEPTH_THREADS=1
EXPOSE 8100
HEALTHCHECK --interval=10s --timeout=3s --start-period=20s --retries=3 \
    CMD ["python", "-c", "import os, sys, urllib.request; sys.exit(0 if urllib.request.urlopen('http://127.0.0.1:%s/readyz' % os.environ.get('DEPTH_PORT', '8100'), timeout=2).status == 200 else 1)"]
ENTRYPOINT ["metricslam", "depth-service"]
