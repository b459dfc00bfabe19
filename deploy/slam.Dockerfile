# SLAM service: Zenoh in/out, local VO + global Sim(3) graph (gtsam), HTTP depth client.
# Installs the core's base dependencies and the slam-service extra (pyproject.toml): no torch, no
# FastAPI, no renderer (numba, scikit-image).
# Build from the repository root:  docker build -f deploy/slam.Dockerfile -t metricslam-slam .
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /app

COPY pyproject.toml README.md ./
COPY shared/ shared/
COPY services/ services/
COPY training/metricslam_train/__init__.py training/metricslam_train/__init__.py
RUN pip install ".[slam-service]" && useradd --system --uid 10001 metricslam \
    && mkdir -p /var/lib/metricslam/state && chown metricslam /var/lib/metricslam/state

USER metricslam
ENV SLAM_ZENOH_ENDPOINT=tcp/zenoh:7447 SLAM_DEPTH_URL=http://depth-lb:8100
HEALTHCHECK --interval=10s --timeout=5s --start-period=20s --retries=3 \
    CMD ["python", "-m", "metricslam_slam.supervisor.healthcheck"]
ENTRYPOINT ["metricslam", "slam-service"]
