"""Reading a sequence's frames so that one bad file costs one frame, not the whole run.

:class:`FrameReader` wraps a :class:`~metricslam.datasets.base.Sequence`. A frame whose files
cannot be read — missing, truncated, corrupt, or not the sequence's image size — is logged once
(index and path), counted, and comes back as an all-black image of the camera's size: the input
the SLAM core already treats as an invalid frame (``TrackingState.INVALID_FRAME``, like a lens
cap), so the run goes on and the frame's pose is interpolated afterwards
(:meth:`metricslam.slam.pipeline.SlamPipeline.trajectory`).

It reads what an estimator uses — the left image, time and camera — and leaves out a
:class:`~metricslam.datasets._common.FileSequence`'s right image and ground-truth depth. While
frame ``i`` is being processed it decodes frame ``i + 1`` on one reader thread (a read-ahead
queue of one frame; PNG decoding releases the GIL), so on two cores decoding overlaps tracking
instead of adding to it. Left images, times and cameras are exactly ``seq[i]``'s, so results do
not change; a frame that is not asked for next is simply read again.

Example::

    reader = FrameReader(open_sequence("SEQ"))
    for i in range(len(reader)):
        session.process(reader[i])
    print(reader.unreadable)  # frame indices that could not be read
    reader.close()             # or use it as a context manager
"""

from __future__ import annotations

import logging
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from metricslam.datasets._common import FileSequence
from metricslam.datasets.base import Frame, Sequence
from metricslam.errors import DatasetError

log = logging.getLogger(__name__)


class FrameReader:
    """Indexable like its sequence; never raises :class:`~metricslam.errors.DatasetError`.
    One consumer thread (the read-ahead slot is not locked).

    Args:
        seq: the sequence to read.
        read_ahead: decode the next frame on a reader thread (see the module doc).

    Attributes:
        unreadable: indices of the frames that could not be read, in the order they were asked for.
    """

    def __init__(self, seq: Sequence, read_ahead: bool = True) -> None:
        self.seq = seq
        self.unreadable: list[int] = []
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="frame-reader") if read_ahead else None
        self._next: tuple[int, Future] | None = None

    def __len__(self) -> int:
        return len(self.seq)

    def __enter__(self) -> "FrameReader":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the reader thread (a read-ahead in progress finishes first)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        self._next = None

    def _read(self, index: int) -> Frame:
        if isinstance(self.seq, FileSequence):  # skip what no estimator reads
            return self.seq.frame(index, extras=False)
        return self.seq[index]

    def __getitem__(self, index: int) -> Frame:
        pending, self._next = self._next, None
        try:
            if pending is not None and pending[0] == index:
                result = pending[1].result()
            else:
                result = self._read(index)
        except DatasetError as exc:
            index = int(index) % len(self.seq)
            self.unreadable.append(index)
            log.warning("frame %d of %s is unreadable, processed as an invalid frame (no pose "
                        "of its own): %s", index, self.seq.name, exc)
            result = invalid_frame(self.seq, index)
        nxt = result.index + 1
        if self._pool is not None and nxt < len(self.seq):
            self._next = (nxt, self._pool.submit(self._read, nxt))
        return result


def invalid_frame(seq: Sequence, index: int) -> Frame:
    """Frame ``index`` of ``seq`` with an all-black (H, W) uint8 image, which SLAM marks invalid."""
    camera = seq.camera
    return Frame(index=index, t_ns=int(seq.t_ns[index]), camera=camera,
                 image=np.zeros((camera.height_px, camera.width_px), np.uint8))
