"""Issue #34 items 3 and 4: the live SLAM service with a saved map, over real components.

A router and client zenoh sessions on loopback (explicit endpoints), the real SLAM service with
real pipeline sessions (learned scale from the in-process depth model, as ``run`` uses), and the
map written by ``metricslam run --save-map``. The scene is ``test_map_relocalize``'s: a 300-frame
rendered loop (seed 3); session 1 (frames 0-149) saves the map offline; session 2 (frames
190-299, renumbered from 0) is replayed into the service, starts outside the map and re-enters
it from behind after ~45 frames.

What must hold (no alignment of session 2 to anything):
* the service publishes a ``relocalized`` status event; every pose before it is in the session's
  own frame (``frame_id "world"``), every pose after it in the map frame (``"map"``), and the
  ``…/trajectory`` answer (``metricslam poses --trajectory``) is the map-frame poses from the
  first localized frame on, like ``run --map``. That frame is within 20 frames (2 s at 10 Hz) of
  the first frame within 10 m of the mapped path — the offline test's bound: it is the frame at
  which the matched keyframe was marginalized, independent of how loaded the machine is;
* the ``…/trajectory`` answer's map-frame positions: RMSE against the truth in the map frame
  within session 1's own RMSE on the revisited stretch + 3 % of that stretch (1.38 + 1.57 m).
  ``test_map_relocalize`` allows 2 % for the *finished* run; the live answer, asked once the back
  end is idle but before the session closes, lacks the final batch solve: measured 2.2-2.7 m here
  against 1.8-1.9 m for the same session closed (in-process, same config);
* the live ``…/pose`` stream in the map frame within 10 m RMSE (unmapped it would be ~40 m off):
  each live pose is mapped by the S_map_world of the matches verified so far, and the back end
  (depth answers, relocalization queries, solves) lags the frames by ~15 frames on this loaded
  machine; measured 5.4 m (~7 m before session 24 fitted the live alignment's scale to the
  matches' spread; docs/maps.md "Not done yet");
* ``…/map/save`` writes the loaded map extended by the session (``tests/test_map_extend.py`` has
  the offline round trip); a save that fails half-way leaves the previous map byte for byte; a
  bad path is one error line, and the service goes on;
* a corrupt map or a newer schema: the service runs without a map (one error line in the health
  answer); a map of another depth model: ``map_refused`` for the camera, which runs without it.
"""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import time

import numpy as np
import pytest
from bench.maps import cut as cut_sequence
from metricslam.datasets import open_sequence
from metricslam.depth import RENDERED_MODEL_PATH
from metricslam.geometry.align import align_trajectory
from metricslam.slam.config_file import load_system_config
from metricslam.slam.graph.config import OFFLINE_DEPTH_QUEUE_SIZE
from metricslam.slam.map.format import load_map
from metricslam.slam.system_config import LIVE_PROFILE
from metricslam.trajectory.io import read_kitti_poses
from metricslam.wire import keys
from metricslam_cli.main import main
from metricslam_slam.service.settings import SlamServiceSettings
from metricslam_slam.service.slam_service import SlamService
from metricslam_slam.supervisor.launcher import free_port
from metricslam_slam.supervisor.router import open_router
from metricslam_slam.tools.client import FramePublisher, PoseRecorder, query_health
from metricslam_slam.zenoh_config import open_client

pytestmark = pytest.mark.slow
START2 = 190
N2 = 300 - START2


@pytest.fixture(scope="module")
def scene(synth_sequence, tmp_path_factory):
    src = synth_sequence(300, seed=3, path="loop")
    root = tmp_path_factory.mktemp("live_map")
    s1 = cut_sequence(src, root / "s1", 0, 150)
    cut_sequence(src, root / "s2", START2, 300)
    assert main(["run", str(s1), "--out", str(root / "s1.txt"), "--json", str(root / "s1.json"),
                 "--deterministic", "--no-progress", "--save-map", str(root / "map"),
                 "--model", str(RENDERED_MODEL_PATH)]) == 0
    return src, root


@pytest.fixture(scope="module")
def stack():
    """``(endpoint, client, start(**settings) -> SlamService)`` on loopback."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(endpoint)
    client = open_client(endpoint)
    services: list[SlamService] = []
    # frames are replayed as fast as zenoh takes them and nothing may be dropped on a loaded machine:
    # the frame queue holds all of them and the depth queue is the offline one
    config = load_system_config(profile=LIVE_PROFILE, overrides={
        "vo": {"preset": "synth"}, "queues": {"frames": 400}, "graph": {"depth_queue_size": OFFLINE_DEPTH_QUEUE_SIZE},
        "depth": {"model_path": str(RENDERED_MODEL_PATH)}})

    def start(**overrides) -> SlamService:
        for old in services:
            old.stop()
        settings = SlamServiceSettings(**{"zenoh_endpoint": endpoint, "depth_url": None, "status_period_s": 0.2,
                                          "hang_timeout_s": 0, **overrides})
        svc = SlamService(settings, config=config).start()
        services.append(svc)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            health = query_health(client, 1.0)
            if health is not None and health.get("instance") == svc.instance:
                return svc
        raise AssertionError("the SLAM service never answered its health query")

    yield endpoint, client, start
    for svc in services:
        svc.stop()
    client.close()
    router.close()


def _replay(client, seq_dir, camera_id: str = "cam0", n: int | None = None,
            recorder: PoseRecorder | None = None) -> int:
    """Publish the folder's frames; with ``recorder``, each once the previous frame's pose arrived
    (a camera the service keeps up with, however loaded the machine)."""
    seq = open_sequence(seq_dir)
    pub = FramePublisher(client, camera_id)
    assert pub.wait_for_subscriber(10), "no SLAM service subscribed to the frames"
    n = len(seq) if n is None else n
    for i in range(n):
        frame = seq[i]
        pub.publish(i, frame.t_ns, frame.image, frame.camera)
        if recorder is not None:
            assert recorder.wait_frames(i + 1, 300), f"no pose for frame {i}"
    pub.close()
    return n


def _events(recorder: PoseRecorder, event: str) -> list[str]:
    return [s.event_detail for s in recorder.statuses_so_far() if s.event == event]


def _save(client, camera_id: str, target) -> tuple[dict | None, str | None]:
    for reply in client.get(keys.map_save_key(camera_id), payload=str(target).encode(), timeout=60.0):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes()), None
        return None, reply.err.payload.to_bytes().decode()
    return None, None


@pytest.fixture(scope="module")
def live(scene, stack):
    """Session 2 replayed into a service with the map; then ``poses --trajectory`` records the
    optimized trajectory once the back end is idle."""
    src, root = scene
    endpoint, client, start = stack
    svc = start(map=root / "map")
    assert svc.health()["map"] == {"path": str(root / "map"), "loaded": True, "error": None,
                                   "keyframes": load_map(root / "map").n_keyframes}
    recorder = PoseRecorder(client, "cam0")
    time.sleep(0.5)  # the recorder's subscriptions reach the service
    _replay(client, root / "s2", recorder=recorder)
    worker = svc._cameras.get("cam0")
    assert worker.with_session(lambda session: session.backend.wait_idle(600))
    out = root / "live.txt"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = main(["poses", "--zenoh-endpoint", endpoint, "--out", str(out), "--timeout", "1",
                     "--camera-id", "cam0", "--trajectory"])
    return svc, recorder, out, {"code": code, "stdout": printed.getvalue()}


def test_the_service_relocalizes_and_publishes_map_frame_poses(scene, live):
    src, root = scene
    svc, recorder, out, result = live
    assert result.get("code") == 0, result
    details = _events(recorder, "relocalized")
    assert len(details) == 1 and str(root / "map") in details[0], details
    frame_ids = [recorder.poses[i].frame_id for i in range(N2)]
    first_map = frame_ids.index("map")
    assert frame_ids == ["world"] * first_map + ["map"] * (N2 - first_map)
    stats = svc.health()
    assert stats["map"]["error"] is None
    # poses --trajectory: map-frame poses from the first localized frame on, as run --map writes
    written = read_kitti_poses(out)
    gt = read_kitti_poses(src / "poses" / "00.txt")
    mapped = gt[:150, :3, 3]
    near = [j for j in range(N2) if np.min(np.linalg.norm(mapped - gt[START2 + j, :3, 3], axis=1)) < 10.0]
    first_localized = N2 - len(written)
    assert near[0] > 20 and first_localized - near[0] <= 20, (near[0], first_localized)
    assert first_localized <= first_map  # the live switch comes once the match is in a solve
    assert f"poses in the map frame from frame {first_localized} on" in result["stdout"], result["stdout"]

    # accuracy in the map frame, the offline test's bound
    s1 = read_kitti_poses(root / "s1.txt")
    st1 = json.loads((root / "s1.json").read_text())
    skip = set(st1["pose_invalid_frame_indices"]) | set(st1["interpolated_frame_indices"])
    revisited = [i for i in range(60) if i not in skip]
    T_gt_map, s1_in_gt = align_trajectory(s1[revisited], gt[revisited], with_scale=False)
    rmse1 = float(np.sqrt(np.mean(np.sum((s1_in_gt[:, :3, 3] - gt[revisited, :3, 3]) ** 2, axis=1))))
    stretch_m = float(np.sum(np.linalg.norm(np.diff(gt[revisited, :3, 3], axis=0), axis=1)))

    def rmse(T_map_cam: np.ndarray, frames: list[int]) -> float:
        in_gt = T_map_cam[:, :3, 3] @ T_gt_map[:3, :3].T + T_gt_map[:3, 3]
        return float(np.sqrt(np.mean(np.sum((in_gt - gt[[START2 + j for j in frames], :3, 3]) ** 2, axis=1))))

    optimized = rmse(written, list(range(first_localized, N2)))
    live_frames = list(range(first_map, N2))
    live_T = np.array([recorder.poses[j].T_world_cam for j in live_frames])
    live_rmse = rmse(live_T, live_frames)
    print(f"map-frame RMSE: optimized {optimized:.2f} m, live {live_rmse:.2f} m, session 1 {rmse1:.2f} m, "
          f"stretch {stretch_m:.1f} m, relocalized at frame {first_localized} (live {first_map})")
    assert optimized <= rmse1 + 0.03 * stretch_m, (optimized, rmse1, stretch_m)
    # each live pose is mapped by the S_map_world of the matches verified so far, against a back
    # end that lags the frames (module docstring); unmapped, they would be ~40 m off
    assert live_rmse <= 10.0, (live_rmse, rmse1, stretch_m)


def test_map_save_query_writes_atomically_and_failures_are_one_line(scene, live, stack, monkeypatch):
    _, root = scene
    _, client, _ = stack
    answer, err = _save(client, "cam0", root / "saved")
    assert err is None and answer["frame_id"] == "map", (answer, err)
    # relocalized: the loaded map extended by the session (map keyframes fixed, then the session's)
    loaded, saved = load_map(root / "map"), load_map(root / "saved")
    ext = answer["extended"]
    assert ext["cross_session_factors"] >= 2 and ext["session_keyframes"] > 5, ext
    assert saved.n_keyframes == answer["keyframes"] == loaded.n_keyframes + ext["session_keyframes"]
    np.testing.assert_array_equal(saved.arrays["keyframes"]["T_map_kf"][:loaded.n_keyframes],
                                  loaded.arrays["keyframes"]["T_map_kf"])
    assert saved.vocabulary_id == loaded.vocabulary_id
    before = {p.name: p.read_bytes() for p in (root / "saved" / "keyframes").iterdir()}

    import metricslam.slam.map.format as fmt

    calls = {"n": 0}
    real = fmt._write_synced

    def dies_half_way(path, data):
        calls["n"] += 1
        if calls["n"] > 5:
            raise OSError(28, "No space left on device")
        real(path, data)

    monkeypatch.setattr(fmt, "_write_synced", dies_half_way)
    answer, err = _save(client, "cam0", root / "saved")
    monkeypatch.undo()
    assert answer is None and "No space left on device" in err and "\n" not in err, err
    assert {p.name: p.read_bytes() for p in (root / "saved" / "keyframes").iterdir()} == before
    load_map(root / "saved")  # still whole

    (root / "a_file").write_text("x")
    answer, err = _save(client, "cam0", root / "a_file" / "map")
    assert answer is None and "cannot write map" in err and "\n" not in err, err
    answer, err = _save(client, "cam0", "")
    assert answer is None and "name the folder" in err, err
    answer, err = _save(client, "nobody", root / "x")
    assert answer is None and "no running SLAM session" in err, err
    assert query_health(client, 2.0)["ready"]


@pytest.mark.parametrize("damage,expected", [
    ("truncate", "does not match its checksum"),
    ("schema", "newer than this metricslam reads"),
    ("missing", "does not exist"),
])
def test_an_unusable_map_is_one_error_line_and_the_service_runs_without_it(scene, live, stack, damage, expected):
    _, root = scene
    _, client, start = stack
    bad = root / f"bad_{damage}"
    shutil.rmtree(bad, ignore_errors=True)
    if damage != "missing":
        shutil.copytree(root / "map", bad)
    if damage == "truncate":
        f = bad / "loop_db" / "bow_rows.npy"
        f.write_bytes(f.read_bytes()[:100])
    elif damage == "schema":
        header = json.loads((bad / "header.json").read_text())
        header["schema_version"] = 99
        (bad / "header.json").write_text(json.dumps(header))
    svc = start(map=bad)
    health = svc.health()["map"]
    assert not health["loaded"] and expected in health["error"] and "\n" not in health["error"], health
    recorder = PoseRecorder(client, "cam1")
    _replay(client, root / "s2", "cam1", n=5)
    assert recorder.wait_frames(5, 120)
    assert {p.frame_id for p in recorder.poses.values()} == {"world"}


def test_a_map_of_another_depth_model_is_refused_for_the_camera(scene, live, stack):
    _, root = scene
    _, client, start = stack
    other = root / "other_model"
    shutil.rmtree(other, ignore_errors=True)
    shutil.copytree(root / "map", other)
    header = json.loads((other / "header.json").read_text())
    header["depth_model_id"] = "sha256:0000000000000000"
    (other / "header.json").write_text(json.dumps(header))
    svc = start(map=other)
    assert svc.health()["map"]["loaded"]  # the header is a valid map: refused per camera
    recorder = PoseRecorder(client, "cam2")
    _replay(client, root / "s2", "cam2", n=5)
    assert recorder.wait_frames(5, 120)
    assert recorder.wait_for(lambda r: _events(r, "map_refused"), 30)
    detail = _events(recorder, "map_refused")[0]
    assert "depth model sha256:0000000000000000" in detail and "runs without the map" in detail, detail
    assert {p.frame_id for p in recorder.poses.values()} == {"world"}


def test_a_camera_carried_back_onto_its_own_map_is_moved_there_live(scene, stack):
    """No map loaded: ``tests/test_segment_relocalization.py``'s kidnap (the loop with frames
    120-264 dropped: the camera put down on lap two, where lap one mapped) replayed into the
    service, then its last image three more times (a camera still streaming, standing still). It
    publishes one ``segment_relocalized`` event; its live poses after that, and its
    ``…/trajectory`` answer for the frames after the gap, are where the truth is (aligned on the
    frames before it), not ~70 m off where the coasting link left them. (A frame is moved by the
    back end's correction when the next frame arrives, so the stream goes on past the event.)"""
    src, root = scene
    endpoint, client, start = stack
    svc = start()
    seq_dir = cut_sequence(src, root / "kidnap", 0, 300, skip=range(120, 265))
    recorder = PoseRecorder(client, "cam1")
    time.sleep(0.5)
    n = _replay(client, seq_dir, camera_id="cam1", recorder=recorder)
    worker = svc._cameras.get("cam1")
    assert worker.with_session(lambda session: session.backend.wait_idle(600))
    deadline = time.monotonic() + 10  # the status message is on its way once the back end is idle
    while not (details := _events(recorder, "segment_relocalized")) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert len(details) == 1 and details[0].startswith("tracking segment 1 relocalized"), details
    last = open_sequence(seq_dir)[n - 1]
    pub = FramePublisher(client, "cam1")
    for k in range(1, 4):
        pub.publish(n - 1 + k, last.t_ns + k * 100_000_000, last.image, last.camera)
        assert recorder.wait_frames(n + k, 300), f"no pose for frame {n - 1 + k}"
    pub.close()
    assert worker.with_session(lambda session: session.backend.wait_idle(600))
    out = root / "kidnap_live.txt"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["poses", "--zenoh-endpoint", endpoint, "--out", str(out), "--timeout", "1",
                     "--camera-id", "cam1", "--trajectory"]) == 0
    gt = read_kitti_poses(seq_dir / "poses" / "00.txt")
    est = read_kitti_poses(out)[:n]
    S, _ = align_trajectory(est[:120], gt[:120])

    def err_m(T: np.ndarray, frame: int) -> float:
        return float(np.linalg.norm(S[:3, :3] @ T[:3, 3] + S[:3, 3] - gt[frame, :3, 3]))

    after = [err_m(est[f], f) for f in range(125, n)]
    assert np.mean(after) < 3.0, " ".join(f"{e:.1f}" for e in after)
    live = [err_m(recorder.poses[n - 1 + k].T_world_cam, n - 1) for k in range(1, 4)]
    assert max(live) < 3.0, live
