"""The image-building half of ``make images-smoke`` (``deploy/images_smoke.py``, issue #35): a base
image made from Debian packages (``debootstrap`` into a ``buildah from scratch`` container), ``buildah
bud`` of the Dockerfiles, working containers mounted and unmounted (:class:`Stack`), the image config
read back (command, user, workdir, env, HEALTHCHECK), the command line that runs a process inside a
mounted image (``unshare --mount`` + ``chroot``), and the cleanup of whatever a step leaves behind
(processes, mounts, working containers, untagged images). Needs root and ``buildah``."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

BASE_IMAGE = "localhost/metricslam-base:bookworm-py3.11"
MIRROR = "http://deb.debian.org/debian"
PATH_ENV = "/usr/local/bin:/usr/local/sbin:/usr/sbin:/usr/bin:/sbin:/bin"
TRIM = ("var/cache/apt/archives/*.deb", "var/cache/apt/*.bin", "var/lib/apt/lists/*", "usr/share/doc",
        "usr/share/man", "usr/share/info", "usr/share/locale")
TOOLS = (("buildah", "apt-get install buildah"), ("debootstrap", "apt-get install debootstrap"),
         ("unshare", "apt-get install util-linux"), ("chroot", "apt-get install coreutils"))
#: mounts for a process in an image's root: a private mount namespace, gone when the process ends
MOUNTS = ('set -e; r=$1; shift; mount -t proc proc "$r/proc"; mount --rbind /dev "$r/dev"; '
          'mount --rbind /sys "$r/sys"; exec "$@"')


class SmokeError(Exception):
    """A step failed; the message says which and why."""


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def _kill_group(proc: subprocess.Popen, grace_s: float = 15.0) -> None:
    for sig, wait in ((signal.SIGTERM, grace_s), (signal.SIGKILL, 10.0)):
        if proc.poll() is not None:
            break
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            break
        try:
            proc.wait(wait)
        except subprocess.TimeoutExpired:
            continue


def run(cmd: list[str], timeout: float, what: str, out: Path | None = None, check: bool = True) -> tuple[int, str]:
    """Run ``cmd`` in its own process group (killed whole on timeout or interrupt); returns
    ``(exit status, output)``; output goes to ``out`` too when given."""
    sink = open(out, "w") if out else subprocess.PIPE  # noqa: SIM115 (closed below)
    proc = subprocess.Popen(cmd, stdout=sink, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        text, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        raise SmokeError(f"{what}: no answer within {timeout:.0f} s ({' '.join(cmd[:3])} …)") from None
    finally:
        _kill_group(proc, 5.0)
        if out:
            sink.close()
    text = out.read_text() if out else text
    if check and proc.returncode != 0:
        tail = "\n".join(text.strip().splitlines()[-15:])
        raise SmokeError(f"{what}: exit {proc.returncode}{f' (log: {out})' if out else ''}\n{tail}")
    return proc.returncode, text



class Stack:
    """Working containers, their mounts and the processes started in them; :meth:`close` removes
    everything (processes first, then mounts left by an interrupted step, then the containers)."""

    def __init__(self, workdir: Path) -> None:
        self.workdir, self.procs, self.containers = workdir, [], {}

    def container(self, image: str) -> tuple[str, Path]:
        """A working container of ``image`` (``scratch``: an empty one), mounted."""
        name = run(["buildah", "from", image], 120, f"buildah from {image}")[1].strip().splitlines()[-1]
        self.containers[name] = None
        self.containers[name] = Path(run(["buildah", "mount", name], 120, f"buildah mount {name}")[1].strip())
        return name, self.containers[name]

    def start(self, name: str, argv: list[str]) -> subprocess.Popen:
        out = open(self.workdir / f"{name}.log", "w")  # noqa: SIM115 (the child keeps it)
        proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        out.close()
        proc.name = name  # type: ignore[attr-defined]
        self.procs.append(proc)
        return proc

    def log_tail(self, name: str, n: int = 15) -> str:
        path = self.workdir / f"{name}.log"
        return "\n".join(path.read_text(errors="replace").strip().splitlines()[-n:]) if path.is_file() else ""

    def stop(self, proc: subprocess.Popen) -> int | None:
        _kill_group(proc)
        return proc.returncode

    def close(self) -> None:
        for proc in reversed(self.procs):
            self.stop(proc)
        for name, mnt in reversed(self.containers.items()):
            if mnt:
                _unmount_under(mnt)
            subprocess.run(["buildah", "umount", name], capture_output=True, timeout=60)
            subprocess.run(["buildah", "rm", name], capture_output=True, timeout=60)


def _unmount_under(root: Path) -> None:
    """Lazily unmount whatever an interrupted step (debootstrap) left mounted below ``root``."""
    mounts = [ln.split()[1] for ln in Path("/proc/mounts").read_text().splitlines()]
    for mnt in sorted((m for m in mounts if m.startswith(f"{root}/")), key=len, reverse=True):
        subprocess.run(["umount", "-l", mnt], capture_output=True, timeout=30)


def in_image(mnt: Path, cfg: dict, argv: list[str], env: dict[str, str]) -> list[str]:
    """The command line that runs ``argv`` in the mounted image as its config says (user, workdir,
    env, plus ``env``), on the host's network."""
    uid, gid, home = 0, 0, "/root"
    user = cfg["user"].split(":")[0]
    if user:
        for line in (mnt / "etc" / "passwd").read_text().splitlines():
            fields = line.split(":")
            if user in (fields[0], fields[2]):
                uid, gid, home = int(fields[2]), int(fields[3]), fields[5]
                break
        else:
            raise SmokeError(f"the image's user {user!r} is not in its /etc/passwd")
    envs = [f"HOME={home}", *cfg["env"], *(f"{k}={v}" for k, v in env.items())]
    return ["unshare", "--mount", "--propagation", "private", "/bin/sh", "-c", MOUNTS, "sh", str(mnt),
            "chroot", f"--userspec={uid}:{gid}", str(mnt), "/usr/bin/env", "-i", "-C", cfg["workdir"], *envs, *argv]


def image_config(image: str) -> dict:
    data = json.loads(run(["buildah", "inspect", "--type", "image", image], 60, f"buildah inspect {image}")[1])
    cfg = (data.get("Docker") or {}).get("config") or data["OCIv1"]["config"]
    test = (cfg.get("Healthcheck") or {}).get("Test") or []
    health = test[1:] if test[:1] == ["CMD"] else (["/bin/sh", "-c", test[1]] if test[:1] == ["CMD-SHELL"] else [])
    return {"command": [*(cfg.get("Entrypoint") or []), *(cfg.get("Cmd") or [])], "env": cfg.get("Env") or [],
            "workdir": cfg.get("WorkingDir") or "/", "user": cfg.get("User") or "", "healthcheck": health}


def image_size_mb(image: str) -> float | None:
    if shutil.which("podman"):
        code, out = run(["podman", "image", "inspect", "--format", "{{.Size}}", image], 60, "podman", check=False)
        if code == 0 and out.strip().isdigit():
            return round(int(out.strip()) / 1e6, 1)
    return None


def image_exists(image: str) -> bool:
    return subprocess.run(["buildah", "inspect", "--type", "image", image], capture_output=True, timeout=60).returncode == 0


def build_base(stack: Stack, timeout: float) -> float:
    """The base image from Debian packages; returns seconds."""
    t0 = time.monotonic()
    name, mnt = stack.container("scratch")
    log(f"debootstrap bookworm into {mnt} (log: {stack.workdir / 'debootstrap.log'})")
    run(["debootstrap", "--variant=minbase", "--include=python3,python3-venv,ca-certificates", "bookworm",
         str(mnt), MIRROR], timeout, "debootstrap", out=stack.workdir / "debootstrap.log")
    for crt in Path("/usr/local/share/ca-certificates").glob("*.crt"):
        shutil.copy2(crt, mnt / "usr" / "local" / "share" / "ca-certificates" / crt.name)
    setup = "python3 -m venv /usr/local && update-ca-certificates >/dev/null && /usr/local/bin/pip --version"
    run(in_image(mnt, {"user": "", "env": [f"PATH={PATH_ENV}"], "workdir": "/"}, ["/bin/sh", "-c", setup], {}),
        300, "venv at /usr/local in the base")
    for pattern in TRIM:
        for path in mnt.glob(pattern):
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            else:
                path.unlink()
    run(["buildah", "config", "--env", f"PATH={PATH_ENV}", "--env", "LANG=C.UTF-8", "--cmd", "python3", name], 60,
        "buildah config")
    run(["buildah", "umount", name], 60, "buildah umount")
    stack.containers[name] = None
    run(["buildah", "commit", "-q", "--rm", "--format", "docker", name, BASE_IMAGE], 600, "buildah commit")
    del stack.containers[name]
    return time.monotonic() - t0


def build_image(stack: Stack, dockerfile: str, tag: str, base: str, timeout: float) -> dict:
    old = image_id(tag) if image_exists(tag) else ""
    out = stack.workdir / f"build-{Path(dockerfile).stem}.log"
    log(f"buildah bud {dockerfile} -> {tag} (log: {out})")
    before, t0 = containers(), time.monotonic()
    try:
        run(["buildah", "bud", "--isolation", "chroot", "--format", "docker", "--build-arg", f"BASE_IMAGE={base}",
             "-f", str(ROOT / dockerfile), "-t", tag, str(ROOT)], timeout, f"build of {dockerfile}", out=out)
    except BaseException:  # a build stopped half-way leaves its working container behind
        for name in containers() - before:
            subprocess.run(["buildah", "rm", name], capture_output=True, timeout=60)
        raise
    seconds = time.monotonic() - t0
    if old and old != image_id(tag):  # the previous build of this tag, now untagged
        subprocess.run(["buildah", "rmi", old], capture_output=True, timeout=120)
    return {"dockerfile": dockerfile, "tag": tag, "build_s": round(seconds, 1), "size_mb": image_size_mb(tag),
            "command": image_config(tag)["command"]}


def containers() -> set[str]:
    out = subprocess.run(["buildah", "containers", "-q", "--notruncate"], capture_output=True, text=True, timeout=60)
    return set(out.stdout.split())


def image_id(image: str) -> str:
    return subprocess.run(["buildah", "inspect", "--type", "image", "--format", "{{.FromImageID}}", image],
                          capture_output=True, text=True, timeout=60).stdout.strip()


def _version(tool: str) -> str | None:
    if not shutil.which(tool):
        return None
    if tool == "debootstrap":
        out = subprocess.run(["dpkg-query", "-W", "-f", "${Version}", "debootstrap"], capture_output=True, text=True)
        return out.stdout.strip() or None
    out = subprocess.run([tool, "--version"], capture_output=True, text=True, timeout=30)
    return out.stdout.strip().split(" version ")[-1].split()[0] if out.returncode == 0 else None
