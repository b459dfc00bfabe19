"""Per-stage tables from py-spy's ``--format raw`` output (collapsed stacks, one per line).

A raw line is ``thread (TID)[: NAME];frame;frame;... COUNT`` (``py-spy record -t -f raw``), each
frame ``function (file:line)``, outermost first. A sample belongs to the stage of the
*innermost* frame that matches one of a table's rules, so ``_add_keyframe -> detect ->
goodFeaturesToTrack`` counts as corner detection and the rest of ``_add_keyframe`` as keyframe
bookkeeping. Samples whose innermost frame is a blocking wait (``Condition.wait``, ``Queue.get``
...) are threads parked on a lock that py-spy did not recognise as idle: they are counted as
``idle wait`` and left out of the shares.

py-spy samples threads that are running *or runnable*: on a machine shared with other jobs a
stage's sample count includes time spent waiting for a core, so shares (not absolute times) are
the comparable numbers between runs.

Example::

    stacks = parse_raw(Path("run.raw").read_text())
    table = aggregate(stacks, SLAM_RULES, rate_hz=200)
"""

from __future__ import annotations

import re
from collections import Counter, defaultdict
from dataclasses import dataclass

IDLE = "idle wait"
OTHER = "other"
#: innermost frames that mean "blocked, not computing" (py-spy sometimes reports them as active)
WAIT_FUNCS = frozenset({"Condition.wait", "Event.wait", "Queue.get", "Thread.join", "Semaphore.acquire",
                        "Thread._wait_for_tstate_lock", "EpollSelector.select", "BaseSelector.select"})
#: leaf frames of idle pool workers (the C call they block in has no Python frame)
WAIT_FRAMES = ("_worker (concurrent/futures/thread.py",)

#: (stage, substrings of a frame: any one matches). First match walking from the leaf outwards.
SLAM_RULES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("decode (dataset reader)", ("load_image (", "load_depth_png (", "FileSequence.__getitem__",
                                 "FrameReader.__getitem__")),
    ("KLT tracking (LK forward + backward)", ("KLTFrontend.track (",)),
    ("corner detection (Shi-Tomasi)", ("KLTFrontend.detect (",)),
    ("essential-matrix RANSAC", ("reject_by_essential (",)),
    ("track prediction (reprojection)", ("predict_pixels (",)),
    ("pose (motion-only BA)", ("estimate_pose (", "relocalize_pnp (", "points_world (")),
    ("window BA", ("bundle_adjust (",)),
    ("marginalization", ("marginalize_oldest (", "marginalization.py", "marginalize (")),
    ("depth network", ("_depth_worker (", "DepthModel.", "InferenceSession")),
    ("loop closure", ("metricslam/slam/loop/",)),
    ("global graph", ("metricslam/slam/graph/",)),
    ("keyframe bookkeeping", ("_add_keyframe (", "_initialize_map (", "try_initialize (",
                              "SlidingWindow.observe (", "_new_reference (")),
    ("start-up (imports, session build)", ("_find_and_load (", "build_session (", "config_from_args (",
                                           "open_sequence (", "load_system_config (")),
    ("trajectory output", ("SlamPipeline.trajectory (", "write_kitti_poses (", "SlamPipeline.close (")),
    ("VO / pipeline glue", ("LocalVO.", "SlamPipeline.", "usable_gray (")),
)

#: the depth service's request path (server process)
DEPTH_RULES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("image header check", ("check_header (", "read_header (")),
    ("decode (imdecode)", ("decode_image (", "decode_gray (")),
    ("resize + normalise", ("DepthModel.preprocess (",)),
    ("network (onnxruntime)", ("InferenceSession", "DepthModel.predict_d_frac (")),
    ("metric inverse depth", ("inv_depth_from_width_fraction (",)),
    ("JSON encode", ("render_json (",)),
    (".npy encode", ("render_npy (",)),
    ("prediction glue", ("DepthPipeline.predict (",)),
    ("metrics (prometheus)", ("prometheus_client/",)),
    ("body receive", ("bodies.py", "receive (")),
    ("admission", ("admission.py",)),
    ("routing + validation (FastAPI)", ("fastapi/", "starlette/", "pydantic")),
    ("HTTP (uvicorn, h11/httptools)", ("uvicorn/", "h11/", "httptools", "connections.py")),
    ("event loop (asyncio)", ("asyncio/",)),
)

_LINE = re.compile(r"^(?P<thread>thread \((?P<tid>\d+)\)(?::\s*(?P<name>[^;]*))?);?(?P<stack>.*) (?P<n>\d+)$")


@dataclass(frozen=True)
class Stack:
    """One collapsed stack: thread id and name (``""`` when py-spy had none), frames outermost
    first, samples."""

    tid: int
    thread: str
    frames: tuple[str, ...]
    samples: int


def parse_raw(text: str) -> list[Stack]:
    """Parse ``py-spy record -t -f raw`` output; thread names are filled in from other lines of
    the same thread id (py-spy names a thread only once it has seen it named)."""
    out: list[Stack] = []
    names: dict[int, str] = {}
    for line in text.splitlines():
        m = _LINE.match(line.strip())
        if not m:
            continue
        tid = int(m["tid"])
        name = (m["name"] or "").strip()
        if name:
            names[tid] = name
        frames = tuple(f for f in m["stack"].split(";") if f)
        out.append(Stack(tid, name, frames, int(m["n"])))
    return [Stack(s.tid, s.thread or names.get(s.tid, f"thread {s.tid}"), s.frames, s.samples) for s in out]


def classify(frames: tuple[str, ...], rules: tuple[tuple[str, tuple[str, ...]], ...]) -> str:
    """The stage of one stack: :data:`IDLE` for a blocking wait at the leaf, else the innermost
    rule match, else :data:`OTHER`."""
    if frames and (frames[-1].split(" (", 1)[0] in WAIT_FUNCS
                   or any(w in frames[-1] for w in WAIT_FRAMES)):
        return IDLE
    for frame in reversed(frames):
        for stage, needles in rules:
            if any(n in frame for n in needles):
                return stage
    return OTHER


def aggregate(stacks: list[Stack], rules: tuple[tuple[str, tuple[str, ...]], ...], rate_hz: float,
              top: int = 4) -> dict:
    """Samples per stage and per thread.

    Returns a JSON-ready dict: ``busy_samples`` (all but idle waits), ``idle_samples``,
    ``stages`` (list of ``{stage, samples, share_pct, thread_s, threads, top_leaves}``, largest
    first; ``thread_s`` = samples / rate, ``top_leaves`` the innermost frames most sampled
    there) and ``threads`` (busy samples per thread name).
    """
    per_stage: Counter[str] = Counter()
    per_thread: Counter[str] = Counter()
    stage_threads: dict[str, Counter[str]] = defaultdict(Counter)
    leaves: dict[str, Counter[str]] = defaultdict(Counter)
    idle = 0
    for s in stacks:
        stage = classify(s.frames, rules)
        if stage == IDLE:
            idle += s.samples
            continue
        per_stage[stage] += s.samples
        per_thread[s.thread] += s.samples
        stage_threads[stage][s.thread] += s.samples
        leaves[stage][s.frames[-1] if s.frames else "?"] += s.samples
    busy = sum(per_stage.values())
    stages = [{"stage": k, "samples": n, "share_pct": 100.0 * n / max(busy, 1), "thread_s": n / rate_hz,
               "threads": dict(stage_threads[k].most_common()),
               "top_leaves": [[leaf, c] for leaf, c in leaves[k].most_common(top)]}
              for k, n in per_stage.most_common()]
    return {"busy_samples": busy, "idle_samples": idle, "rate_hz": rate_hz, "stages": stages,
            "threads": dict(per_thread.most_common())}


def merge(tables: list[dict]) -> dict:
    """Sum several :func:`aggregate` results of the same rules and rate (repeated runs)."""
    if not tables:
        raise ValueError("merge needs at least one table")
    rate = tables[0]["rate_hz"]
    samples: Counter[str] = Counter()
    threads: Counter[str] = Counter()
    stage_threads: dict[str, Counter[str]] = defaultdict(Counter)
    leaves: dict[str, Counter[str]] = defaultdict(Counter)
    for t in tables:
        threads.update(t["threads"])
        for row in t["stages"]:
            samples[row["stage"]] += row["samples"]
            stage_threads[row["stage"]].update(row["threads"])
            leaves[row["stage"]].update({leaf: c for leaf, c in row["top_leaves"]})
    busy = sum(samples.values())
    stages = [{"stage": k, "samples": n, "share_pct": 100.0 * n / max(busy, 1), "thread_s": n / rate,
               "threads": dict(stage_threads[k].most_common()),
               "top_leaves": [[leaf, c] for leaf, c in leaves[k].most_common(4)]}
              for k, n in samples.most_common()]
    return {"busy_samples": busy, "idle_samples": sum(t["idle_samples"] for t in tables), "rate_hz": rate,
            "stages": stages, "threads": dict(threads.most_common()), "runs": len(tables)}
