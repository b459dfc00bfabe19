"""``make images-smoke``: build both container images and start what they contain, with no container
engine (issue #35). Needs root, ``buildah``, ``debootstrap`` (and ``podman`` for exact image sizes).

1. A base image made from Debian packages (registry images such as ``python:3.11-slim`` may be out
   of reach): ``debootstrap --variant=minbase --include=python3,python3-venv bookworm`` into a
   ``buildah from scratch`` container, a venv at ``/usr/local`` (``python``/``pip`` on PATH, site
   packages where python:3.11-slim has them), this machine's extra CA certificates
   (``/usr/local/share/ca-certificates``: pip in the RUN steps must trust the network's TLS), docs
   and apt lists trimmed; committed as ``localhost/metricslam-base:bookworm-py3.11`` and reused by
   later runs unless ``--rebuild-base``.
2. ``buildah bud --isolation chroot --format docker --build-arg BASE_IMAGE=…`` of
   ``deploy/depth.Dockerfile`` and ``deploy/slam.Dockerfile`` (``podman run`` is refused on some
   machines, RLIMIT_NPROC; chroot isolation runs the RUN steps without a runtime).
3. Each image's own command (ENTRYPOINT + CMD, user, workdir, env, HEALTHCHECK read from the image
   config) started inside its mounted root filesystem (``buildah mount``; ``unshare --mount`` +
   ``chroot``, /proc, /dev and /sys in a private mount namespace that ends with the process; host
   network, loopback, free ports; the environment of docker-compose.yml with loopback endpoints):
   the depth image answers ``/readyz``, a KITTI PNG and its own health check; a zenoh router from
   the SLAM image, the SLAM image's command behind it, its health check, and the host's
   ``metricslam poses`` + ``metricslam replay`` of a KITTI sequence (06) through that router; then
   the SLAM image with ``SLAM_ROS2=1`` must start (health check passes, a short replay is
   answered) or exit with a message naming SLAM_ROS2.

Writes ``bench/results/images_smoke.json`` (+ ``.md``); ``python -m bench.make_results`` renders it
into docs/deployment.md. Every wait has a timeout; child processes, mounts and working containers
are removed on exit (also on Ctrl-C / SIGTERM).

    sudo .venv/bin/python -m deploy.images_smoke ../shared/data/kitti_odometry/sequences/06
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import tomllib
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # run as a file, not with -m from the repository root
    sys.path.insert(0, str(ROOT))

from bench.machine import command_line, describe, write_results  # noqa: E402
from bench.results_common import _load, _src  # noqa: E402
from deploy.images_build import (  # noqa: E402  (buildah/debootstrap: building, mounting, cleanup)
    BASE_IMAGE,
    TOOLS,
    SmokeError,
    Stack,
    _version,
    build_base,
    build_image,
    image_config,
    image_exists,
    image_id,
    image_size_mb,
    in_image,
    log,
    run,
)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]



def wait_for(check, timeout: float, what: str, stack: Stack, proc: subprocess.Popen | None = None,
             period: float = 1.0) -> float:
    """Poll ``check()`` until true; returns the seconds it took. Fails when ``proc`` exits first."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if check():
            return time.monotonic() - t0
        if proc is not None and proc.poll() is not None:
            raise SmokeError(f"{what}: {proc.name} exited ({proc.returncode}) first:\n{stack.log_tail(proc.name)}")
        time.sleep(period)
    tail = f":\n{stack.log_tail(proc.name)}" if proc is not None else ""
    raise SmokeError(f"{what}: not within {timeout:.0f} s{tail}")


def http(url: str, body: bytes | None = None, content_type: str = "", timeout: float = 60.0) -> tuple[int, bytes]:
    req = urllib.request.Request(url, data=body, headers={"Content-Type": content_type} if content_type else {})
    try:
        with urllib.request.urlopen(req, timeout=timeout) as resp:
            return resp.status, resp.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()
    except (urllib.error.URLError, OSError):
        return 0, b""


def compose_env(service: str) -> dict[str, str]:
    doc = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    return {k: str(v) for k, v in (doc["services"][service].get("environment") or {}).items()}


def kitti_fx(seq: Path) -> float:
    p0 = next(ln for ln in (seq / "calib.txt").read_text().splitlines() if ln.startswith("P0:"))
    return float(p0.split()[1])


def path_length(rows: np.ndarray) -> float:
    t = rows.reshape(-1, 3, 4)[:, :, 3]
    return float(np.linalg.norm(np.diff(t, axis=0), axis=1).sum())


def smoke_depth(stack: Stack, image: str, seq: Path, port: int, timeout: float) -> dict:
    cfg = image_config(image)
    _, mnt = stack.container(image)
    env = {**compose_env("depth"), "DEPTH_HOST": "127.0.0.1", "DEPTH_PORT": str(port)}
    proc = stack.start("depth", in_image(mnt, cfg, cfg["command"], env))
    url = f"http://127.0.0.1:{port}"
    ready_s = wait_for(lambda: http(f"{url}/readyz", timeout=5)[0] == 200, timeout, "depth /readyz", stack, proc)
    log(f"depth image: /readyz 200 after {ready_s:.1f} s")
    png, fx = seq / "image_0" / "000000.png", kitti_fx(seq)
    t0 = time.monotonic()
    status, body = http(f"{url}/v1/disparity?fx={fx}", png.read_bytes(), "image/png", timeout=120)
    post_ms = 1000 * (time.monotonic() - t0)
    if status != 200:
        raise SmokeError(f"depth POST {png.name}: HTTP {status}: {body[:300]!r}")
    answer = json.loads(body)
    inv = np.asarray(answer["inv_depth_per_m"], dtype=float)
    health = run(in_image(mnt, cfg, cfg["healthcheck"], env), 60, "depth HEALTHCHECK", check=False)[0]
    if health != 0:
        raise SmokeError(f"depth image: its HEALTHCHECK exited {health} while /readyz answers")
    log(f"depth image: {png.name} -> {inv.shape[1]}x{inv.shape[0]} inverse depth in {post_ms:.0f} ms; HEALTHCHECK 0")
    return {"passed": True, "readyz_s": round(ready_s, 1), "png": f"{seq.name}/image_0/{png.name}",
            "post_status": status, "post_ms": round(post_ms), "grid": f"{inv.shape[1]}x{inv.shape[0]}",
            "median_depth_m": round(float(np.nanmedian(1.0 / inv[inv > 0])), 1), "healthcheck_rc": health}


def start_slam(stack: Stack, image: str, name: str, env: dict[str, str], timeout: float) -> tuple:
    cfg = image_config(image)
    _, mnt = stack.container(image)
    proc = stack.start(name, in_image(mnt, cfg, cfg["command"], env))
    health = in_image(mnt, cfg, cfg["healthcheck"], env)
    return proc, wait_for(lambda: run(health, 60, "slam HEALTHCHECK", check=False)[0] == 0 or proc.poll() is not None,
                          timeout, f"{name}: HEALTHCHECK", stack, period=2.0)


def replay(stack: Stack, seq: Path, endpoint: str, frames: int, timeout: float, camera: str, name: str,
           trajectory: bool = True) -> dict:
    """Replay ``frames`` frames of ``seq`` into the stack and record them: the live stream's pose
    states and, with ``trajectory`` (a run long enough for metric scale), the optimized
    trajectory's path and scale error against the KITTI poses."""
    cli = str(Path(sys.executable).parent / "metricslam")
    live, out = stack.workdir / f"{name}_poses.txt", stack.workdir / f"{name}_trajectory.txt"
    recorder = [cli, "poses", "--zenoh-endpoint", endpoint, "--frames", str(frames), "--timeout", str(int(timeout)),
                "--camera-id", camera]
    poses = stack.start(f"{name}-poses", [*recorder, "--out", str(live)])  # the pose states of the live stream
    optimized = stack.start(f"{name}-trajectory", [*recorder, "--out", str(out), "--trajectory"]) if trajectory else None
    time.sleep(3.0)  # the recorder's subscription is declared before the first frame
    t0 = time.monotonic()
    code, text = run([cli, "replay", str(seq), "--zenoh-endpoint", endpoint, "--max-frames", str(frames),
                      "--max-in-flight", "4", "--camera-id", camera, "--no-progress", "--wait", "120"],
                     timeout, f"{name}: metricslam replay", out=stack.workdir / f"{name}-replay.log", check=False)
    replay_s = time.monotonic() - t0
    try:
        poses.wait(60)
        if optimized is not None:
            optimized.wait(60)
    except subprocess.TimeoutExpired:
        raise SmokeError(f"{name}: metricslam poses did not finish 60 s after the replay") from None
    summary = stack.log_tail(f"{name}-poses", 40)
    states = dict((k, int(v)) for v, k in re.findall(r"(\d+) (unscaled|provisional|metric)", summary))
    result = {"frames": frames, "replay_rc": code, "poses_rc": max(poses.returncode, optimized.returncode if optimized else 0),
              "replay_s": round(replay_s, 1),
              "unscaled": states.get("unscaled"), "provisional": states.get("provisional"), "metric": states.get("metric")}
    if code != 0 or result["poses_rc"] != 0 or not states.get("metric", 0) + states.get("provisional", 0):
        raise SmokeError(f"{name}: replay exit {code}, poses exit {poses.returncode}:\n"
                         f"{stack.log_tail(f'{name}-replay')}\n{summary}")
    gt = seq.parent.parent / "poses" / f"{seq.name}.txt"
    if trajectory and out.is_file() and gt.is_file():
        from metricslam.evaluation.evaluator import evaluate_poses
        from metricslam.trajectory.io import read_kitti_poses

        skip = states.get("unscaled", 0)  # placeholder lines of frames without a metric pose
        est, ref = np.loadtxt(out)[skip:], np.loadtxt(gt)[:frames][skip:]
        result["path_m"], result["gt_path_m"] = round(path_length(est), 1), round(path_length(ref), 1)
        T_est, T_gt = read_kitti_poses(out)[skip:], read_kitti_poses(gt)[:frames][skip:]
        if len(T_est) == len(T_gt) >= 3:
            ev = evaluate_poses(T_gt, T_est, name=seq.name)
            error = ev.result.scale_error_pct
            result["scale_error_pct"] = None if error is None else round(error, 1)
    return result


def ros2_topics(endpoint: str) -> list[str]:
    """The ROS 2 topics published through ``endpoint``, from rmw_zenoh's liveliness tokens (what
    ``ros2 topic list`` sees); asked from the host."""
    import zenoh

    from metricslam_slam.zenoh_config import session_config

    with zenoh.open(session_config("client", connect=[endpoint])) as session:
        keys = [str(r.ok.key_expr) for r in session.liveliness().get("@ros2_lv/**", timeout=10.0) if r.ok]
    return sorted({k.split("/")[9].replace("%", "/") for k in keys if k.split("/")[5:6] == ["MP"]})


def smoke_slam(stack: Stack, image: str, seq: Path, depth_port: int, args: argparse.Namespace) -> tuple[dict, dict]:
    cfg = image_config(image)
    _, mnt = stack.container(image)
    rport = free_port()
    endpoint = f"tcp/127.0.0.1:{rport}"
    router = stack.start("router", in_image(mnt, cfg, ["python", "-m", "metricslam_slam.supervisor.router",
                                                       "--listen", endpoint], {}))
    wait_for(lambda: "READY" in stack.log_tail("router"), 120, "zenoh router (from the SLAM image)", stack, router)
    log(f"zenoh router from the SLAM image on {endpoint}")
    env = {**compose_env("slam"), "SLAM_ZENOH_ENDPOINT": endpoint, "SLAM_DEPTH_URL": f"http://127.0.0.1:{depth_port}"}
    frames = args.frames or len(list((seq / "image_0").glob("*.png")))
    proc, ready_s = start_slam(stack, image, "slam", env, args.start_timeout)
    if proc.poll() is not None:
        raise SmokeError(f"slam image: its command exited ({proc.returncode}):\n{stack.log_tail('slam')}")
    log(f"slam image: HEALTHCHECK 0 after {ready_s:.1f} s; replaying {frames} frames of {seq.name}")
    slam = {"passed": True, "ready_s": round(ready_s, 1), "sequence": seq.name,
            **replay(stack, seq, endpoint, frames, args.replay_timeout, "cam0", "slam")}
    log(f"slam image: {slam}")
    stack.stop(proc)
    proc, ready_s = start_slam(stack, image, "slam-ros2", {**env, "SLAM_ROS2": "1"}, args.start_timeout)
    if proc.poll() is not None:
        tail = stack.log_tail("slam-ros2", 5)
        clear = proc.returncode != 0 and "SLAM_ROS2" in tail and "Traceback" not in stack.log_tail("slam-ros2", 200)
        ros2 = {"passed": clear, "outcome": "refused", "exit": proc.returncode, "message": tail.splitlines()[-1:]}
        if not clear:
            raise SmokeError(f"slam image with SLAM_ROS2=1 exited {proc.returncode} without a clear message:\n{tail}")
    else:
        ros2 = {"outcome": "started", "ready_s": round(ready_s, 1),
                **replay(stack, seq, endpoint, min(frames, 10), args.replay_timeout, "ros2cam", "slam-ros2",
                         trajectory=False)}
        ros2["ros2_topics"] = ros2_topics(endpoint)
        ros2["passed"] = bool(ros2["ros2_topics"])
        if not ros2["passed"]:
            raise SmokeError("slam image with SLAM_ROS2=1 started, but the router knows no ROS 2 publisher")
    log(f"slam image with SLAM_ROS2=1: {ros2}")
    return slam, ros2


def preflight(seq: Path) -> None:
    if os.geteuid() != 0:
        raise SmokeError("run as root (buildah mount, chroot and unshare need it): sudo make images-smoke")
    for tool, fix in TOOLS:
        if not shutil.which(tool):
            raise SmokeError(f"{tool} not found: {fix}")
    if not (seq / "image_0" / "000000.png").is_file() or not (seq / "calib.txt").is_file():
        raise SmokeError(f"{seq}: not a KITTI sequence folder (image_0/000000.png, calib.txt); pass e.g. "
                         "../shared/data/kitti_odometry/sequences/06")
    if not (Path(sys.executable).parent / "metricslam").is_file():
        raise SmokeError("no metricslam command next to this Python: make install (the host runs replay/poses)")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("seq", type=Path, help="KITTI odometry sequence folder (06: ../shared/data/kitti_odometry/sequences/06)")
    p.add_argument("--frames", type=int, default=0, help="frames to replay (default: 0, every frame)")
    p.add_argument("--rebuild-base", action="store_true", help="rebuild the Debian base image even if present")
    p.add_argument("--base", default=BASE_IMAGE, help="base image (default: %(default)s, built when missing)")
    p.add_argument("--build-timeout", type=float, default=1800, help="seconds per image build (default: %(default)s)")
    p.add_argument("--start-timeout", type=float, default=300, help="seconds for a service to become ready "
                   "(default: %(default)s)")
    p.add_argument("--replay-timeout", type=float, default=900, help="seconds for a replay (default: %(default)s)")
    p.add_argument("--out", default=str(ROOT / "bench" / "results" / "images_smoke"),
                   help="results path without suffix (default: bench/results/images_smoke)")
    args = p.parse_args(argv)
    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, lambda signum, _f: sys.exit(128 + signum))
    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    result: dict = {"version": version, "base": {"image": args.base}, "images": {}, "smoke": {}, "passed": False}
    seq = args.seq.resolve()
    try:
        preflight(seq)
    except SmokeError as exc:
        print(f"images-smoke: {exc}", file=sys.stderr)
        return 1
    workdir = Path(tempfile.mkdtemp(prefix="images-smoke-"))
    stack, t_start = Stack(workdir), time.monotonic()
    machine, old_base = describe(), ""  # the load before the builds: this machine is often shared
    try:
        if args.rebuild_base or not image_exists(args.base):
            if args.base != BASE_IMAGE:
                raise SmokeError(f"base image {args.base} not found (only {BASE_IMAGE} is built here)")
            old_base = image_id(args.base) if image_exists(args.base) else ""
            result["base"]["build_s"] = round(build_base(stack, args.build_timeout), 1)
            log(f"base image {args.base}: {result['base']['build_s']} s")
        result["base"]["size_mb"] = image_size_mb(args.base)
        for name in ("depth", "slam"):
            image = build_image(stack, f"deploy/{name}.Dockerfile", f"localhost/metricslam-{name}:{version}",
                                args.base, args.build_timeout)
            result["images"][name] = image
            log(f"{name} image: built in {image['build_s']} s, {image['size_mb']} MB")
        if old_base and old_base != image_id(args.base):  # the replaced base, unused once both are rebuilt
            subprocess.run(["buildah", "rmi", old_base], capture_output=True, timeout=120)
        depth_port = free_port()
        result["smoke"]["depth"] = smoke_depth(stack, result["images"]["depth"]["tag"], seq, depth_port,
                                               args.start_timeout)
        result["smoke"]["slam"], result["smoke"]["slam_ros2"] = smoke_slam(
            stack, result["images"]["slam"]["tag"], seq, depth_port, args)
        result["passed"] = all(s["passed"] for s in result["smoke"].values())
    except SmokeError as exc:
        result["error"] = str(exc).splitlines()[0]
        print(f"images-smoke: FAILED: {exc}\n(logs: {workdir})", file=sys.stderr)
    except (KeyboardInterrupt, SystemExit):
        print(f"images-smoke: interrupted; stopping what it started (logs: {workdir})", file=sys.stderr)
        raise
    finally:  # also on Ctrl-C / SIGTERM: no process, mount or working container is left behind
        stack.close()
    result["total_s"] = round(time.monotonic() - t_start, 1)
    payload = {**result, "command": command_line("deploy.images_smoke", argv), "machine": machine,
               "tools": {t: _version(t) for t in ("buildah", "debootstrap", "podman")}}
    write_results(args.out, payload, images_smoke_block(payload))
    log(f"wrote {args.out}.json; images-smoke {'passed' if result['passed'] else 'FAILED'} in "
        f"{result['total_s']:.0f} s (logs: {workdir})")
    return 0 if result["passed"] else 1



def images_smoke_block(data: dict | None = None) -> str:
    """The generated block of docs/deployment.md: both images built and started without a container
    engine (``make images-smoke``, ``deploy/images_smoke.py``; ``bench/results/images_smoke.json``)."""
    data = data or _load("images_smoke.json")
    if not data:
        return ""
    base, smoke = data["base"], data.get("smoke", {})
    built = f"{base['build_s']:.0f} s" if "build_s" in base else "present, reused"
    rows = ["| image | from | build | size | command |", "| --- | --- | --- | --- | --- |",
            f"| `{base['image']}` | Debian bookworm packages (debootstrap minbase + python3, python3-venv) | "
            f"{built} | {base.get('size_mb')} MB | |"]
    rows += [f"| `{i['tag']}` | `{i['dockerfile']}` | {i['build_s']:.0f} s | {i['size_mb']} MB | `{' '.join(i['command'])}` |"
             for i in data["images"].values()]
    d, s, r = (smoke.get(k) for k in ("depth", "slam", "slam_ros2"))
    said = [f"Smoke **{'passed' if data['passed'] else 'FAILED: ' + data.get('error', '?')}** in {data['total_s']:.0f} s."]
    if d:
        said.append(f"Depth image: `/readyz` 200 after {d['readyz_s']} s; POST of KITTI `{d['png']}` → HTTP "
                    f"{d['post_status']}, {d['grid']} inverse depth (median {d['median_depth_m']} m) in {d['post_ms']} ms; "
                    f"its HEALTHCHECK exits {d['healthcheck_rc']}.")
    for what, x in (("SLAM image", s), ("SLAM image with `SLAM_ROS2=1`", r)):
        if x and "frames" in x:
            said.append(f"{what} (router: the SLAM image's): HEALTHCHECK passes after {x['ready_s']} s; {x['frames']} frames "
                        f"replayed in {x['replay_s']} s → {x['metric']} metric, {x['provisional']} provisional, "
                        f"{x['unscaled']} unscaled poses"
                        + (f"; the optimized trajectory (`poses --trajectory`): path {x['path_m']} m (ground truth "
                           f"{x.get('gt_path_m')} m), scale error {x.get('scale_error_pct')} %" if "path_m" in x else "")
                        + (f"; ROS 2 topics announced: {', '.join(f'`{t}`' for t in x['ros2_topics'])}." if x.get("ros2_topics") else "."))
        elif x:
            said.append(f"{what}: {x['outcome']}, exit {x.get('exit')}: `{' '.join(x.get('message', []))}`.")
    tools = ", ".join(f"{k} {v}" for k, v in data.get("tools", {}).items() if v)
    return "\n".join([*rows, "", " ".join(said), "", f"{_src('images_smoke.json', data)}; {tools}; "
                      f"machine: {data.get('machine', '?')}"]) + "\n"


if __name__ == "__main__":
    sys.exit(main())
