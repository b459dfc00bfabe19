"""Micro-batching in the depth service (``metricslam_depth.batcher``): concurrent requests share
one network run and each gets its own rows; a failed run fails every request in it."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from metricslam_depth.batcher import MicroBatcher


def _network(calls: list[int]):
    def run(images, cameras):
        calls.append(len(images))
        return np.stack([np.full((2, 3), float(im[0, 0])) for im in images])
    return run


def test_concurrent_requests_share_one_network_run_and_get_their_own_rows() -> None:
    calls: list[int] = []
    batcher = MicroBatcher(_network(calls), window_s=0.2)
    got: dict[int, np.ndarray] = {}
    barrier = threading.Barrier(3)

    def request(k: int) -> None:
        barrier.wait()
        got[k] = batcher.predict([np.full((4, 4), k, np.uint8), np.full((4, 4), 10 + k, np.uint8)], None)

    threads = [threading.Thread(target=request, args=(k,)) for k in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(5)
    assert calls == [6] and batcher.runs == 1
    for k in range(3):
        assert got[k].shape == (2, 2, 3) and got[k][0, 0, 0] == k and got[k][1, 0, 0] == 10 + k


def test_a_run_never_exceeds_max_images_and_a_lone_request_runs_alone() -> None:
    calls: list[int] = []
    batcher = MicroBatcher(_network(calls), window_s=0.2, max_images=4)
    barrier = threading.Barrier(3)
    threads = [threading.Thread(target=lambda: (barrier.wait(), batcher.predict([np.zeros((4, 4), np.uint8)] * 2, None)))
               for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(5)
    assert sorted(calls) == [2, 4]
    calls.clear()
    assert batcher.predict([np.ones((4, 4), np.uint8)], None)[0, 0, 0] == 1.0 and calls == [1]


def test_a_failed_run_fails_each_request_in_it() -> None:
    def broken(images, cameras):
        raise ValueError("network failed")

    batcher = MicroBatcher(broken, window_s=0.01)
    with pytest.raises(ValueError, match="network failed"):
        batcher.predict([np.zeros((4, 4), np.uint8)], None)
    with pytest.raises(ValueError):  # and the next request is not stuck behind it
        batcher.predict([np.zeros((4, 4), np.uint8)], None)


def test_the_service_with_a_batch_window_answers_as_without() -> None:
    """Real services (uvicorn on loopback): two concurrent requests to one with
    ``DEPTH_BATCH_WINDOW_MS`` (the setting reaches the pipeline; sharing a run is the tests above)
    get the same answers as from a service without it."""
    import cv2
    import httpx

    from tests.depth_service_process import ServiceProcess

    rng = np.random.default_rng(0)
    image = cv2.GaussianBlur(rng.integers(0, 255, (188, 620), dtype=np.uint8), (7, 7), 2)
    ok, png = cv2.imencode(".png", image)
    body = png.tobytes()

    def ask(port: int) -> np.ndarray:
        r = httpx.post(f"http://127.0.0.1:{port}/v1/disparity", content=body, params={"fx": 360.0},
                       headers={"Content-Type": "image/png"}, timeout=30)
        assert r.status_code == 200, r.text
        return np.asarray(r.json()["inv_depth_per_m"], dtype=np.float32)

    with ServiceProcess(18120) as plain:
        expected = ask(plain.port)
    with ServiceProcess(18121, settings={"batch_window_ms": 50}) as batched:
        got: list[np.ndarray] = []
        barrier = threading.Barrier(2)
        threads = [threading.Thread(target=lambda: (barrier.wait(), got.append(ask(batched.port)))) for _ in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(30)
        assert batched.process is not None
    assert ok and len(got) == 2
    for answer in got:
        np.testing.assert_allclose(answer, expected, rtol=1e-5, atol=1e-6)
