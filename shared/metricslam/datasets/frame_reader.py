"""Reading a sequence's frames so that one bad file costs one frame, not the whole run.

:class:`FrameReader` wraps a :class:`~metricslam.datasets.base.Sequence`. A frame whose files
cannot be read — missing, truncated, corrupt, or not the sequence's image size — is logged once
(index and path), counted, and comes back as an all-black image of the camera's size: the input
the SLAM core already treats as an invalid frame (``TrackingState.INVALID_FRAME``, like a lens
cap), so the run goes on and the frame's pose is interpolated afterwards
(:meth:`metricslam.slam.pipeline.SlamPipeline.trajectory`).

Example::

    reader = FrameReader(open_sequence("SEQ"))
    for i in range(len(reader)):
        session.process(reader[i])
    print(reader.unreadable)  # frame indices that could not be read
"""

from __future__ import annotations

import logging

import numpy as np

from metricslam.datasets.base import Frame, Sequence
from metricslam.errors import DatasetError

log = logging.getLogger(__name__)


class FrameReader:
    """Indexable like its sequence; never raises :class:`~metricslam.errors.DatasetError`.

    Args:
        seq: the sequence to read.

    Attributes:
        unreadable: indices of the frames that could not be read, in the order they were asked for.
    """

    def __init__(self, seq: Sequence) -> None:
        self.seq = seq
        self.unreadable: list[int] = []

    def __len__(self) -> int:
        return len(self.seq)

    def __getitem__(self, index: int) -> Frame:
        try:
            return self.seq[index]
        except DatasetError as exc:
            index = int(index) % len(self.seq)
            self.unreadable.append(index)
            log.warning("frame %d of %s is unreadable, processed as an invalid frame (no pose "
                        "of its own): %s", index, self.seq.name, exc)
            return invalid_frame(self.seq, index)


def invalid_frame(seq: Sequence, index: int) -> Frame:
    """Frame ``index`` of ``seq`` with an all-black (H, W) uint8 image, which SLAM marks invalid."""
    camera = seq.camera
    return Frame(index=index, t_ns=int(seq.t_ns[index]), camera=camera,
                 image=np.zeros((camera.height_px, camera.width_px), np.uint8))
