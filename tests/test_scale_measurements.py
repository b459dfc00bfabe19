"""``bench/scale_measurements.py``: the SLAM's own scale measurements against the truth.

On a rendered drive whose depth source is the renderer's exact depth, every learned scale
measurement is right by construction, so the bench must find the "network" right at the
landmarks (ratio 1 in every populated bin), the per-keyframe measured scale equal to the true
one, and the LiDAR-slot reference (the rendered ``depth_0/``) agreeing with the stereo one.
A bench that matched landmarks to the wrong frame, pixels or filter would fail here.
"""

from __future__ import annotations

import pytest
from bench.scale_measurements import evaluate
from metricslam.datasets import open_sequence
from test_session_builder import RenderedDepth


@pytest.mark.slow
def test_exact_depth_gives_unit_ratios(synth_sequence):
    seq_dir = synth_sequence(60, seed=3, path="loop")
    res = evaluate([str(seq_dir)], None, depth_source=RenderedDepth(open_sequence(seq_dir)))
    (seq,) = res["sequences"].values()
    for ref in ("stereo", "lidar"):
        a = seq[ref]
        assert a["keyframes"] >= 10 and a["landmarks"] >= 200
        assert a["net_over_ref_all"] == pytest.approx(1.0, abs=0.03), ref
        assert a["measured_over_true_median"] == pytest.approx(1.0, abs=0.03), ref
        assert a["optimized_over_true_median"] == pytest.approx(1.0, abs=0.08), ref
        for label, b in a["bins"].items():
            if b["n"] >= 30:
                assert b["net_over_ref"] == pytest.approx(1.0, abs=0.06), (ref, label)
                assert b["vo_over_ref"] == pytest.approx(1.0, abs=0.06), (ref, label)
