"""The VO's output does not depend on when its background window solve finishes
(``VOConfig.ba_joins_next_frame``): the frame after a keyframe waits for that keyframe's solve.

Without it a threaded ``metricslam run`` moved by points of scale error from run to run, by which
frames happened to be tracked against a solved map (``bench/results/threaded_spread_*.md``).
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from metricslam.datasets.base import Frame
from metricslam.slam.types import TrackingState
from metricslam.slam.vo.config import VOConfig
from metricslam.slam.vo.local_vo import LocalVO

N_FRAMES = 36


@pytest.fixture(scope="module")
def scene():
    from metricslam.synth import SynthConfig, SynthScene
    scene = SynthScene.procedural(frames=N_FRAMES, seed=3, path="turns",
                                  config=SynthConfig(width_px=620, height_px=188))
    return scene, [scene.frame(i).left for i in range(N_FRAMES)]


def _run(scene, images, delay_s: float, **vo: object) -> np.ndarray:
    """Poses (N, 4, 4) of a background-BA VO whose every window solve takes ``delay_s`` longer."""
    cam = scene.camera
    local = LocalVO(VOConfig.preset("synth", ba_in_background=True, **vo), cam)
    solve = local.window.optimize_and_marginalize

    def slow_solve() -> None:
        time.sleep(delay_s)
        solve()

    local.window.optimize_and_marginalize = slow_solve
    ests = [local.process(Frame(index=i, t_ns=i * 100_000_000, image=img, camera=cam))
            for i, img in enumerate(images)]
    local.close()
    assert [e.state for e in ests].count(TrackingState.TRACKING) > N_FRAMES // 2
    assert sum(e.is_keyframe for e in ests) >= 3
    return np.array([e.T_world_cam for e in ests])


@pytest.mark.slow
def test_poses_do_not_depend_on_how_long_the_background_solve_takes(scene) -> None:
    fast = _run(*scene, delay_s=0.0)
    slow = _run(*scene, delay_s=0.15)
    np.testing.assert_array_equal(fast, slow)
    # without the join, frames tracked while the solve is still running see the unsolved map:
    # the same input gives another trajectory (this is what the join removes)
    unjoined = _run(*scene, delay_s=0.15, ba_joins_next_frame=False)
    assert not np.array_equal(fast, unjoined)
