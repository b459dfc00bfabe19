"""Deployment files validated offline (there is no cluster and no Docker engine here).

* ``deploy/k8s/``: every manifest validates against the JSON schemas of pinned Kubernetes
  versions (``kubernetes-validate``, which ships them in its wheel; strict mode, so an unknown or
  misspelt field is an error), the kustomization lists exactly the manifests that exist, and the
  pieces refer to each other correctly (selectors, probe ports, HPA target, headless Service,
  environment variables that are real settings, URLs that name the Services, resource comments
  that quote the bench results).
* ``docker-compose.yml`` against the Compose specification's JSON schema as vendored by
  ``check-jsonschema`` (tests/test_compose.py adds the typed ``compose-spec`` parser).

Not done here: ``kustomize build`` / ``kubectl apply --dry-run=server`` (no binaries, no API
server), building or running the images.
"""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path

import pytest
import yaml

kv = pytest.importorskip("kubernetes_validate", reason="pip install kubernetes-validate (dev extra)")

from metricslam_depth.settings import DepthServiceSettings  # noqa: E402
from metricslam_slam.service.settings import SlamServiceSettings  # noqa: E402

#: the Kubernetes versions the manifests must be valid for: a conservative one and the newest
#: the pinned kubernetes-validate ships schemas for
K8S_VERSIONS = ("1.33.0", "1.37.0")


@pytest.fixture(scope="module")
def k8s_dir(repo_root: Path) -> Path:
    return repo_root / "deploy" / "k8s"


@pytest.fixture(scope="module")
def kustomization(k8s_dir: Path) -> dict:
    return yaml.safe_load((k8s_dir / "kustomization.yaml").read_text())


@pytest.fixture(scope="module")
def docs(k8s_dir: Path, kustomization: dict) -> list[dict]:
    out = []
    for name in kustomization["resources"]:
        out += [d for d in yaml.safe_load_all((k8s_dir / name).read_text()) if d]
    return out


def by_kind(docs: list[dict], kind: str, name: str) -> dict:
    (doc,) = [d for d in docs if d["kind"] == kind and d["metadata"]["name"] == name]
    return doc


def test_kustomization_lists_every_manifest(k8s_dir: Path, kustomization: dict, docs: list[dict]) -> None:
    assert kustomization["kind"] == "Kustomization"
    on_disk = {p.name for p in k8s_dir.glob("*.yaml")} - {"kustomization.yaml"}
    assert set(kustomization["resources"]) == on_disk
    kinds = {(d["kind"], d["metadata"]["name"]) for d in docs}
    assert {("Deployment", "zenoh"), ("Service", "zenoh"), ("Deployment", "depth"), ("Service", "depth"),
            ("HorizontalPodAutoscaler", "depth"), ("StatefulSet", "slam"), ("Service", "slam")} <= kinds
    used = {c["image"].split(":")[0] for d in docs if d["kind"] in ("Deployment", "StatefulSet")
            for c in d["spec"]["template"]["spec"]["containers"]}
    assert {i["name"] for i in kustomization["images"]} <= used


@pytest.mark.parametrize("version", K8S_VERSIONS)
def test_manifests_validate_against_the_pinned_kubernetes_schemas(docs: list[dict], version: str) -> None:
    for doc in docs:
        kv.validate(doc, version, strict=True)


def test_the_validator_rejects_broken_manifests(docs: list[dict]) -> None:
    depth = by_kind(docs, "Deployment", "depth")
    typo = json.loads(json.dumps(depth))
    typo["spec"]["replica"] = typo["spec"].pop("replicas")
    with pytest.raises(kv.ValidationError):
        kv.validate(typo, K8S_VERSIONS[0], strict=True)
    wrong_type = json.loads(json.dumps(depth))
    wrong_type["spec"]["template"]["spec"]["containers"][0]["ports"][0]["containerPort"] = "http"
    with pytest.raises(kv.ValidationError):
        kv.validate(wrong_type, K8S_VERSIONS[0], strict=True)


def test_services_select_their_pods_and_probes_use_named_ports(docs: list[dict]) -> None:
    workloads = [d for d in docs if d["kind"] in ("Deployment", "StatefulSet")]
    for svc in (d for d in docs if d["kind"] == "Service"):
        matches = [w for w in workloads
                   if svc["spec"]["selector"].items() <= w["spec"]["template"]["metadata"]["labels"].items()]
        assert len(matches) == 1, svc["metadata"]["name"]
        ports = {p["name"] for c in matches[0]["spec"]["template"]["spec"]["containers"] for p in c.get("ports", [])}
        for p in svc["spec"].get("ports", []):
            assert p["targetPort"] in ports
    for w in workloads:
        assert w["spec"]["selector"]["matchLabels"].items() <= w["spec"]["template"]["metadata"]["labels"].items()
        for c in w["spec"]["template"]["spec"]["containers"]:
            assert c["resources"]["requests"]["cpu"] and c["resources"]["requests"]["memory"]
            names = {p["name"] for p in c.get("ports", [])}
            for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
                for kind in ("httpGet", "tcpSocket"):
                    if kind in c.get(probe, {}):
                        assert c[probe][kind]["port"] in names, (c["name"], probe)


def test_depth_probes_hpa_and_cited_measurements(docs: list[dict], k8s_dir: Path, repo_root: Path) -> None:
    from metricslam_depth.routes import router

    (c,) = by_kind(docs, "Deployment", "depth")["spec"]["template"]["spec"]["containers"]
    assert c["readinessProbe"]["httpGet"]["path"] == "/readyz"
    assert c["livenessProbe"]["httpGet"]["path"] == "/healthz"
    assert {"/readyz", "/healthz"} <= {r.path for r in router.routes}
    hpa = by_kind(docs, "HorizontalPodAutoscaler", "depth")
    assert hpa["spec"]["scaleTargetRef"] == {"apiVersion": "apps/v1", "kind": "Deployment", "name": "depth"}
    assert hpa["spec"]["minReplicas"] >= 2 and hpa["spec"]["metrics"][0]["resource"]["name"] == "cpu"
    # the resource comment quotes the bench result file it cites
    bench = json.loads((repo_root / "bench" / "results" / "depth_service.json").read_text())
    text = (k8s_dir / "depth.yaml").read_text()
    assert "bench/results/depth_service.json" in text
    json_levels = [lv for lv in bench["levels"] if lv["form"] == "json"]
    for level in json_levels:
        assert f"{level['server_cpu_ms_per_req']:.2f}" in text
    assert f"{bench['soak']['rss_before_mib']:.0f}" in text
    pgm = json.loads((repo_root / "bench" / "results" / "depth_service_pgm_input.json").read_text())
    assert "bench/results/depth_service_pgm_input.json" in text
    for level in (lv for lv in pgm["levels"] if lv["form"] == "json"):
        assert f"{level['server_cpu_ms_per_req']:.2f}" in text


def test_slam_state_volume_and_environment(docs: list[dict], monkeypatch) -> None:
    slam = by_kind(docs, "StatefulSet", "slam")
    assert by_kind(docs, "Service", slam["spec"]["serviceName"])["spec"]["clusterIP"] == "None"
    (claim,) = slam["spec"]["volumeClaimTemplates"]
    (c,) = slam["spec"]["template"]["spec"]["containers"]
    assert {m["name"] for m in c["volumeMounts"]} == {claim["metadata"]["name"]}
    env = {e["name"]: e["value"] for e in c["env"]}
    for name, value in env.items():
        if name.startswith("SLAM_"):
            assert name[5:].lower() in SlamServiceSettings.model_fields, name
            monkeypatch.setenv(name, value)
    settings = SlamServiceSettings()
    zenoh_port = by_kind(docs, "Service", "zenoh")["spec"]["ports"][0]["port"]
    depth_port = by_kind(docs, "Service", "depth")["spec"]["ports"][0]["port"]
    assert settings.zenoh_endpoint == f"tcp/zenoh:{zenoh_port}"
    assert settings.depth_url == f"http://depth:{depth_port}"
    (d,) = by_kind(docs, "Deployment", "depth")["spec"]["template"]["spec"]["containers"]
    for e in d["env"]:
        assert e["name"][6:].lower() in DepthServiceSettings.model_fields, e["name"]


def compose_schema() -> dict:
    pytest.importorskip("check_jsonschema", reason="pip install check-jsonschema (dev extra)")
    path = resources.files("check_jsonschema.builtin_schemas.vendor") / "compose-spec.json"
    return json.loads(path.read_text())


def test_compose_file_validates_against_the_compose_spec_schema(repo_root: Path) -> None:
    import jsonschema

    schema = compose_schema()
    validator = jsonschema.validators.validator_for(schema)(schema)
    compose = yaml.safe_load((repo_root / "docker-compose.yml").read_text())
    errors = sorted(validator.iter_errors(compose), key=str)
    assert not errors, [e.message for e in errors]
    compose["services"]["depth"]["healthcheck"]["intervall"] = "10s"  # a typo must be caught
    assert any(validator.iter_errors(compose))


def test_every_container_has_limits_and_a_pinned_image(docs: list[dict], kustomization: dict) -> None:
    import metricslam

    for w in (d for d in docs if d["kind"] in ("Deployment", "StatefulSet")):
        for c in w["spec"]["template"]["spec"]["containers"]:
            assert c["resources"]["limits"]["cpu"] and c["resources"]["limits"]["memory"], c["name"]
            image = c["image"]
            assert not image.endswith(":latest"), image
    tags = {i["name"]: i["newTag"] for i in kustomization["images"]}
    assert tags == {"metricslam-depth": metricslam.__version__, "metricslam-slam": metricslam.__version__}


def test_slam_liveness_probe_is_local_and_works(docs: list[dict], tmp_path: Path) -> None:
    """The StatefulSet's liveness probe checks the watchdog's heartbeat file, not the router (a
    router outage must not restart SLAM); the command it runs answers 0 with a fresh heartbeat and
    1 with a stale one."""
    import os
    import subprocess
    import sys
    import time

    from metricslam_slam.service.watchdog import write_heartbeat

    (c,) = by_kind(docs, "StatefulSet", "slam")["spec"]["template"]["spec"]["containers"]
    command = c["livenessProbe"]["exec"]["command"]
    assert "--alive" in command and "--zenoh-endpoint" not in command
    env = {e["name"]: e["value"] for e in c["env"]}
    assert float(env["SLAM_HANG_TIMEOUT_S"]) > 0
    beat = tmp_path / "alive"
    run_env = {**os.environ, "SLAM_HEARTBEAT_FILE": str(beat),
               "SLAM_ZENOH_ENDPOINT": "tcp/127.0.0.1:1"}
    cmd = [sys.executable if part == "python" else part for part in command]
    write_heartbeat(beat)
    assert subprocess.run(cmd, env=run_env, capture_output=True, timeout=60).returncode == 0
    write_heartbeat(beat, now_s=time.time() - 3600)
    assert subprocess.run(cmd, env=run_env, capture_output=True, timeout=60).returncode == 1
