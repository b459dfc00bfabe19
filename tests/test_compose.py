"""The compose deployment, validated offline (no Docker engine here).

* the compose file parses under the Compose specification (``compose-spec``: a strict,
  typed parser — unknown keys, wrong types and dangling references are errors);
* every build context, Dockerfile and COPY source exists;
* images never install torch; settings in ``environment`` are real settings fields;
* the long-running services have health checks; depth runs replicated behind the LB;
* the effective limits: every service has CPU and memory limits, nginx's body limit is at least
  the depth service's largest accepted request, no image is ``:latest``.
"""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

compose_spec = pytest.importorskip("compose_spec", reason="pip install compose-spec (dev extra)")

from metricslam.slam.config_file import load_system_config  # noqa: E402
from metricslam_depth.settings import DepthServiceSettings  # noqa: E402
from metricslam_slam.service.settings import SlamServiceSettings  # noqa: E402


def interpolate(text: str, env: dict[str, str] | None = None) -> str:
    """What ``docker compose`` does to ``${NAME:-default}`` / ``${NAME}`` before parsing
    (``compose-spec`` parses the file as written)."""
    env = {} if env is None else env
    return re.sub(r"\$\{(\w+)(?::-([^}]*))?\}", lambda m: env.get(m[1]) or (m[2] or ""), text)


@pytest.fixture(scope="module")
def compose(repo_root: Path) -> dict:
    text = interpolate((repo_root / "docker-compose.yml").read_text())
    parsed = compose_spec.PyCompose.from_yaml(text)
    parsed.validate()
    return yaml.safe_load(text)


def test_ports_are_published_on_loopback_unless_configured(repo_root: Path) -> None:
    raw = (repo_root / "docker-compose.yml").read_text()
    published = [p for svc in yaml.safe_load(interpolate(raw))["services"].values() for p in svc.get("ports", [])]
    assert sorted(published) == ["127.0.0.1:7447:7447", "127.0.0.1:8100:8100"]
    opened = yaml.safe_load(interpolate(raw, {"METRICSLAM_PUBLISH_ADDRESS": "0.0.0.0"}))
    assert opened["services"]["zenoh"]["ports"] == ["0.0.0.0:7447:7447"]
    compose_spec.PyCompose.from_yaml(interpolate(raw, {"METRICSLAM_PUBLISH_ADDRESS": "0.0.0.0"})).validate()


def _copy_sources(dockerfile: Path) -> list[str]:
    sources = []
    for line in dockerfile.read_text().splitlines():
        if not line.split(maxsplit=1)[:1] or line.split(maxsplit=1)[0].upper() not in ("COPY", "ADD"):
            continue
        parts = shlex.split(line, comments=True)
        if parts and parts[0].upper() in ("COPY", "ADD"):
            args = [a for a in parts[1:] if not a.startswith("--")]
            if any(a.startswith("--from") for a in parts[1:]):
                continue
            sources += args[:-1]
    return sources


def test_compose_file_is_valid_spec(compose: dict) -> None:
    assert set(compose["services"]) == {"zenoh", "depth", "depth-lb", "slam"}
    assert compose["services"]["zenoh"]["image"].startswith("eclipse/zenoh:")


def test_strict_parser_rejects_a_broken_file(repo_root: Path) -> None:
    text = interpolate((repo_root / "docker-compose.yml").read_text())
    with pytest.raises(ValueError):
        compose_spec.PyCompose.from_yaml(text.replace("restart: unless-stopped", "restart_policy: x", 1))
    with pytest.raises(ValueError):
        compose_spec.PyCompose.from_yaml(text.replace("replicas: 2", "replicas: two"))


def test_builds_and_copy_sources_exist(compose: dict, repo_root: Path) -> None:
    built = [s for s in compose["services"].values() if "build" in s]
    assert len(built) == 2
    for service in built:
        context = repo_root / service["build"]["context"]
        dockerfile = context / service["build"]["dockerfile"]
        assert dockerfile.is_file(), dockerfile
        text = dockerfile.read_text()
        run_lines = [ln for ln in text.splitlines() if not ln.lstrip().startswith("#")]
        assert not any("torch" in ln.lower() or "[train" in ln for ln in run_lines), dockerfile
        assert "HEALTHCHECK" in text
        sources = _copy_sources(dockerfile)
        assert sources, f"{dockerfile} copies nothing"
        for src in sources:
            assert (context / src).exists(), f"{dockerfile.name}: COPY source {src} missing"
        # the entry point is the `metricslam` console script: the image must hold its package's folder
        assert "cli/" in sources, f"{dockerfile.name} does not copy cli/ (metricslam_cli)"
    for service in compose["services"].values():
        for volume in service.get("volumes", []):
            host = volume.split(":")[0]
            if host.startswith("."):
                assert (repo_root / host).exists(), host


@pytest.mark.parametrize(("dockerfile", "extras", "not_there"), [
    ("depth.Dockerfile", "depth-service", ("eclipse-zenoh", "httpx")),
    # the ros extra: what SLAM_ROS2=1 needs (rosbags, mcap), so the variable works in the image
    ("slam.Dockerfile", "slam-service,ros", ("fastapi", "uvicorn")),
])
def test_images_install_their_component_extra(repo_root: Path, dockerfile: str, extras: str,
                                               not_there: tuple[str, ...]) -> None:
    """Each image installs the core's base dependencies plus its own extras, no package by hand;
    neither carries torch, the renderer (numba, scikit-image), matplotlib nor the viewer."""
    import tomllib

    project = tomllib.loads((repo_root / "pyproject.toml").read_text())["project"]
    text = (repo_root / "deploy" / dockerfile).read_text()
    installs = [ln for ln in text.splitlines() if ln.startswith("RUN") and "pip install" in ln]
    assert len(installs) == 1 and f'pip install ".[{extras}]"' in installs[0], installs
    deps = list(project["dependencies"])
    for extra in extras.split(","):
        deps += project["optional-dependencies"][extra]
    packages = [re.split(r"[\[<>=~! ;]", d, maxsplit=1)[0].lower() for d in deps]
    for name in ("torch", "numba", "scikit-image", "matplotlib", "rerun-sdk", *not_there):
        assert name not in packages, f"{dockerfile}: {name} would be installed"


def test_environment_names_are_settings_fields(compose: dict) -> None:
    fields = {"SLAM_": set(SlamServiceSettings.model_fields), "DEPTH_": set(DepthServiceSettings.model_fields)}
    seen = 0
    for service in compose["services"].values():
        for name in service.get("environment", {}):
            for prefix, names in fields.items():
                if name.startswith(prefix):
                    assert name[len(prefix):].lower() in names, f"{name} is not a setting"
                    seen += 1
            if name.startswith("METRICSLAM_"):
                assert "__" in name, f"{name} is not a METRICSLAM_<SECTION>__<FIELD> variable"
                seen += 1
    assert seen >= 8


def test_environment_builds_valid_settings(compose: dict, monkeypatch) -> None:
    environment = {name: str(value) for name, value in compose["services"]["slam"]["environment"].items()}
    for name, value in environment.items():
        monkeypatch.setenv(name, value)
    settings = SlamServiceSettings()
    assert settings.zenoh_endpoint == "tcp/zenoh:7447" and settings.depth_url == "http://depth-lb:8100"
    # the SLAM state is on a named volume, so a restarted container continues its cameras
    assert settings.state_dir is not None
    mounts = {m.split(":")[1]: m.split(":")[0] for m in compose["services"]["slam"]["volumes"]}
    assert mounts[str(settings.state_dir)] in compose["volumes"]
    config = load_system_config(env=environment)  # every METRICSLAM_* variable is a real field
    assert config.vo.preset == "kitti" and config.use_scale and config.queues.frames == 8


def test_health_replicas_and_load_balancer(compose: dict, repo_root: Path) -> None:
    services = compose["services"]
    for name in ("depth", "depth-lb", "slam"):
        assert "healthcheck" in services[name], name
    assert services["depth"]["deploy"]["replicas"] >= 2
    assert "ports" not in services["depth"]  # replicas are reached through the LB only
    assert services["slam"]["depends_on"]["depth-lb"]["condition"] == "service_healthy"
    nginx = (repo_root / "deploy" / "nginx-depth.conf").read_text()
    assert re.search(r"server\s+depth:8100", nginx)
    lb_url = services["slam"]["environment"]["SLAM_DEPTH_URL"]
    assert lb_url.startswith("http://depth-lb:")


def test_slam_healthcheck_fails_without_a_router() -> None:
    out = subprocess.run([sys.executable, "-m", "metricslam_slam.supervisor.healthcheck", "--zenoh-endpoint",
                          "tcp/127.0.0.1:17499"], capture_output=True, timeout=60)
    assert out.returncode == 1


def _bytes(size: str) -> int:
    """nginx size syntax (``16m``, ``512k``, ``1g``, bytes) in bytes."""
    m = re.fullmatch(r"(\d+)([kKmMgG]?)", size)
    assert m, size
    return int(m[1]) * {"": 1, "k": 1024, "m": 1024**2, "g": 1024**3}[m[2].lower()]


def test_every_service_has_cpu_and_memory_limits(compose: dict) -> None:
    for name, service in compose["services"].items():
        limits = service.get("deploy", {}).get("resources", {}).get("limits", {})
        assert float(limits.get("cpus", 0)) > 0, f"{name}: no CPU limit"
        assert re.fullmatch(r"\d+[MG]", str(limits.get("memory", ""))), f"{name}: no memory limit"


def test_nginx_body_limit_covers_the_largest_depth_request(compose: dict, repo_root: Path, monkeypatch) -> None:
    """A request the depth service (as compose configures it) would accept is never cut off by
    nginx's HTML 413: the service answers what is too large itself, in problem+json."""
    for name, value in compose["services"]["depth"]["environment"].items():
        monkeypatch.setenv(name, str(value))
    depth = DepthServiceSettings()
    nginx = (repo_root / "deploy" / "nginx-depth.conf").read_text()
    (size,) = re.findall(r"^\s*client_max_body_size\s+(\S+);", nginx, flags=re.M)
    largest = max(depth.max_body_bytes, depth.max_batch_body_bytes)
    assert _bytes(size) >= largest, f"nginx client_max_body_size {size} < {largest} B the service accepts"
    assert _bytes("16m") < largest  # the former limit, which cut large batches off


def test_images_are_pinned_never_latest(compose: dict, repo_root: Path) -> None:
    import metricslam

    raw = (repo_root / "docker-compose.yml").read_text()
    for name, service in compose["services"].items():
        image = service["image"]
        assert ":" in image and not image.endswith(":latest"), f"{name}: {image}"
    built = {name: s["image"] for name, s in compose["services"].items() if "build" in s}
    assert {image.split(":")[1] for image in built.values()} == {metricslam.__version__}
    assert "${METRICSLAM_VERSION:-" + metricslam.__version__ + "}" in raw
    assert yaml.safe_load(interpolate(raw, {"METRICSLAM_VERSION": "9.9.9"}))["services"]["slam"]["image"] \
        == "metricslam-slam:9.9.9"


def test_router_health_check_and_hung_slam_restart(compose: dict) -> None:
    """The router has a health check; the SLAM service's watchdog is on, so a hung service exits
    and ``restart: unless-stopped`` restarts it (compose never restarts an unhealthy container)."""
    services = compose["services"]
    zenoh = services["zenoh"]
    assert "healthcheck" in zenoh and zenoh["healthcheck"]["test"][0] == "CMD"
    rest = zenoh["command"][zenoh["command"].index("--rest-http-port") + 1]
    assert rest.startswith("127.0.0.1:")  # the REST admin interface stays inside the container
    assert rest.split(":")[1] in " ".join(zenoh["healthcheck"]["test"])
    slam = services["slam"]
    env = {k: str(v) for k, v in slam["environment"].items()}
    assert float(env["SLAM_HANG_TIMEOUT_S"]) > 0 and env["SLAM_HEARTBEAT_FILE"]
    for service in services.values():
        assert service["restart"] == "unless-stopped"
