# SLAM service: Zenoh in/out, local VO + global Sim(3) graph (gtsam), HTTP depth client.
# Installs the core's base dependencies, the slam-service extra and the ros extra (pyproject.toml;
# rosbags + mcap, pure Python: what SLAM_ROS2=1 needs, so the ROS 2 bridge works in this image):
# no torch, no FastAPI, no renderer (numba, scikit-image).
# Build from the repository root:  docker build -f deploy/slam.Dockerfile -t metricslam-slam:0.1.0 .
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
RUN pip install ".[slam-service,ros]" && useradd --system --uid 10001 metricslam \
    && mkdir -p /var/lib/metricslam/state && chown metricslam /var/lib/metricslam/state

USER metricslam
ENV SLAM_ZENOH_ENDPOINT=tcp/zenoh:7447 SLAM_DEPTH_URL=http://depth-lb:8100 \
    SLAM_HEARTBEAT_FILE=/tmp/metricslam-alive
HEALTHCHECK --interval=10s --timeout=5s --start-period=20s --retries=3 \
    CMD ["python", "-m", "metricslam_slam.supervisor.healthcheck"]
ENTRYPOINT ["metricslam", "slam-service"]
