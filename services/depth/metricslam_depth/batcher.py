"""Micro-batching across requests: one network run for the images of concurrent requests.

``DEPTH_BATCH_WINDOW_MS`` > 0 turns it on. The first request to reach the network (the leader)
waits the window for others, then runs the network once on every image queued meanwhile and
hands each request its own rows; the others (followers) wait for their rows instead of running
the network themselves. Requests still decode, map back and encode on their own worker threads,
in parallel; only the network call is shared.

Whether it pays depends on the machine: a batched run amortises per-call overhead, but while
the leader runs it the followers' threads idle. Measured on the 2-core dev machine
(``docs/depth_service.md``, ``bench/results/depth_service_batching_*.md``); the default is off.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

#: the network: (images, cameras or None) -> (B, h, w) rows in the same order
RunNetwork = Callable[[list[np.ndarray], list | None], np.ndarray]


@dataclass
class _Job:
    images: list[np.ndarray]
    cameras: list | None
    done: threading.Event = field(default_factory=threading.Event)
    rows: np.ndarray | None = None
    error: BaseException | None = None


class MicroBatcher:
    """Shares network runs between concurrent callers (module docstring).

    Args:
        run: the network call for a list of images (and their cameras, version-2 models).
        window_s: how long the leader waits for other requests' images.
        max_images: most images in one network run; beyond it a new run starts.
    """

    def __init__(self, run: RunNetwork, window_s: float, max_images: int = 8) -> None:
        self._run = run
        self._window_s = float(window_s)
        self._max_images = int(max_images)
        self._lock = threading.Lock()
        self._queue: list[_Job] = []
        self._collecting = False
        self.runs = 0  # network runs made (tests, metrics)

    def predict(self, images: list[np.ndarray], cameras: list | None) -> np.ndarray:
        """Rows (len(images), h, w) for these images; blocks until their run is done.

        Raises:
            Whatever the network call raised for the run these images were in.
        """
        job = _Job(list(images), cameras)
        with self._lock:
            self._queue.append(job)
            lead = not self._collecting
            self._collecting = True
        if lead:
            time.sleep(self._window_s)
            self._drain()
        job.done.wait()
        if job.error is not None:
            raise job.error
        return job.rows

    def _drain(self) -> None:
        """Run the network on the queued jobs, ``max_images`` at a time, until none is left."""
        while True:
            with self._lock:
                batch, n = [], 0
                while self._queue and (not batch or n + len(self._queue[0].images) <= self._max_images):
                    n += len(self._queue[0].images)
                    batch.append(self._queue.pop(0))
                if not batch:
                    self._collecting = False
                    return
            images = [im for job in batch for im in job.images]
            with_cameras = batch[0].cameras is not None
            cameras = [c for job in batch for c in job.cameras] if with_cameras else None
            try:
                rows = self._run(images, cameras)
                self.runs += 1
                start = 0
                for job in batch:
                    job.rows = rows[start:start + len(job.images)]
                    start += len(job.images)
            except BaseException as exc:  # noqa: BLE001 -- every caller in the run gets it
                for job in batch:
                    job.error = exc
            for job in batch:
                job.done.set()
