"""``bench/landmark_depth.py``: the landmark-depth selection metric (network vs GT-triangulated corners).

A short rendered drive (``metricslam.synth``, exact poses and depth, world seed 3 — the depth
network's synthetic training worlds use seeds 11–16) must give a triangulated reference that
matches the rendered depth at the corners and an SGBM oracle near 1; the per-bin bookkeeping and
:func:`summary` are checked on results with known answers.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from bench import gt_corners
from bench import landmark_depth as ld

FRAMES = 13  # stride 3, gap 3: 4 frame pairs


@pytest.fixture(scope="module")
def drive(synth_sequence) -> Path:
    return synth_sequence(FRAMES, seed=3, path="loop")


@pytest.fixture(scope="module")
def samples(drive):
    from metricslam.datasets import open_sequence
    from metricslam.depth import DepthModel

    seq = open_sequence(drive, poses_file=drive / "poses" / "00.txt")
    return seq, ld.landmark_samples(seq, DepthModel.load(threads=1))


def test_triangulation_recovers_exact_depth_and_rejects_no_parallax() -> None:
    rng = np.random.default_rng(0)
    K = np.array([[700.0, 0, 600], [0, 700.0, 180], [0, 0, 1]])
    X = np.column_stack([rng.uniform(-8, 8, 200), rng.uniform(-2, 2, 200), rng.uniform(5, 55, 200)])

    def project(T_cam_a, pts):
        q = pts @ T_cam_a[:3, :3].T + T_cam_a[:3, 3]
        return (q @ K.T)[:, :2] / q[:, 2:]

    T_b_a = np.eye(4)
    T_b_a[:3, 3] = [0.2, 0.0, -3.5]  # b is 3.5 m ahead (and a little to the side)
    keep, z = gt_corners.triangulate_gt(project(np.eye(4), X), project(T_b_a, X), K, T_b_a, min_parallax_deg=0.0)
    assert keep.all()
    np.testing.assert_allclose(z, X[:, 2], rtol=1e-6)
    # the parallax floor drops points near the focus of expansion, not the well-conditioned ones
    keep_1, _ = gt_corners.triangulate_gt(project(np.eye(4), X), project(T_b_a, X), K, T_b_a, min_parallax_deg=1.0)
    assert 0 < keep_1.sum() < keep.sum()
    # points behind the second camera are rejected
    X_near = X[:5] * [1, 1, 0] + [0, 0, 3.0]
    assert not gt_corners.triangulate_gt(project(np.eye(4), X_near), project(T_b_a, X_near), K, T_b_a,
                                 min_parallax_deg=0.0)[0].any()
    # a standing car: any depth reprojects exactly, none may be accepted
    keep_0, _ = gt_corners.triangulate_gt(project(np.eye(4), X), project(np.eye(4), X), K, np.eye(4))
    assert not keep_0.any()


def test_triangulated_corners_match_the_rendered_depth(samples) -> None:
    seq, s = samples
    assert s["pairs"] == 4 and s["z_tri"].size > 200
    assert ((s["z_tri"] >= 2) & (s["z_tri"] <= 60)).all()
    # independent of the module's own depth_0 sampling: the rendered depth at the nearest pixel
    u, v = np.rint(s["u"]).astype(int), np.rint(s["v"]).astype(int)
    true = np.array([seq[f].depth_m[r, c] for f, c, r in zip(s["frame"].astype(int), u, v)])
    ok = true > 0
    ratio = s["z_tri"][ok] / true[ok]
    assert abs(np.median(ratio) - 1) < 0.02
    # single corners are noisy (KLT ~0.5 px over 3 frames at 620 px; corners on depth edges may
    # read the other side), but most are close
    assert np.mean(np.abs(ratio - 1) < 0.1) > 0.65
    # and no range bin is biased (noise moving corners across bin edges would show here)
    check = ld.per_bin(s["z_tri"], s["z_depth0"])
    populated = [b for b in ld.BIN_LABELS if check[b]["n"] >= 50]
    assert len(populated) >= 3
    for b in populated:
        assert abs(check[b]["median"] - 1) < 0.03, (b, check[b])


def test_sgbm_oracle_is_near_one_and_bins_add_up(samples) -> None:
    _, s = samples
    oracle = ld.per_bin(s["z_tri"], s["z_oracle"])
    assert oracle["all"]["n"] > 100
    assert abs(oracle["all"]["median"] - 1) < 0.05
    assert oracle["all"]["p25"] <= oracle["all"]["median"] <= oracle["all"]["p75"]
    net = ld.per_bin(s["z_tri"], s["z_net"])
    assert sum(net[b]["n"] for b in ld.BIN_LABELS) == net["all"]["n"] == s["z_tri"].size
    # the oracle leaves out corners in empty cells, never adds any
    assert all(oracle[b]["n"] <= net[b]["n"] for b in ld.BIN_LABELS)


def test_per_bin_edges() -> None:
    z_ref = np.array([1.9, 2.0, 4.99, 5.0, 20.0, 59.9, 60.0, 60.1])
    idx = ld.bin_index(z_ref)
    np.testing.assert_array_equal(idx, [-1, 0, 0, 1, 3, 4, 4, -1])
    res = ld.per_bin(z_ref, 2 * z_ref)
    assert res["all"]["n"] == 6 and res["all"]["median"] == pytest.approx(2.0)
    assert res["10-20"] == {"n": 0, "median": None, "p25": None, "p75": None}


def _bins(**medians_and_counts) -> dict:
    out = {b: {"n": 0, "median": None, "p25": None, "p75": None} for b in (*ld.BIN_LABELS, "all")}
    for key, (median, n) in medians_and_counts.items():
        out[key.removeprefix("b").replace("_", "-")] = {"n": n, "median": median, "p25": median, "p75": median}
    return out


def test_summary_takes_the_worst_populated_bin() -> None:
    net = _bins(b2_5=(3.0, 500),     # near bin: not in the summary
                b5_10=(1.10, 50),
                b10_20=(0.80, 400),  # |log 0.8| = 0.223: the worst counted
                b20_40=(1.20, 300),  # |log 1.2| = 0.182
                b40_60=(0.5, 19))    # too few corners
    res = {"sequences": {"a": {"name": "a", "network": net},
                         "b": {"name": "b", "network": _bins(b20_40=(1.0, 30))}}}
    out = ld.summary(res)
    assert out["a"]["worst_bin"] == "10-20"
    assert out["a"]["worst_abs_log_ratio"] == pytest.approx(abs(math.log(0.8)))
    assert set(out["a"]["abs_log_ratio"]) == {"5-10", "10-20", "20-40"}
    assert out["b"]["worst_abs_log_ratio"] == pytest.approx(0.0)
    assert ld.summary({"sequences": {"c": {"name": "c", "network": _bins(b40_60=(2.0, 5))}}})["c"] == {
        "worst_abs_log_ratio": None, "worst_bin": None, "abs_log_ratio": {}}


def test_main_writes_json_and_markdown_with_the_command(drive, tmp_path) -> None:
    out = tmp_path / "ld"
    argv = ["--seq", str(drive), "--gt", str(drive / "poses" / "00.txt"), "--name", "t", "--slam",
            "--out", str(out)]
    assert ld.main(argv) == 0
    data = json.loads(out.with_suffix(".json").read_text())
    md = out.with_suffix(".md").read_text()
    assert data["command"].endswith("-m bench.landmark_depth " + " ".join(argv))
    assert data["command"] in md
    (name, res), = data["sequences"].items()
    assert data["model"]["path"].endswith("depth_l3_int8.onnx")
    assert sum(res["network"][b]["n"] for b in ld.BIN_LABELS) == res["corners"]
    frac = res["slam"]["fraction"]
    assert res["slam"]["landmarks"] > 50
    assert sum(frac.values()) == pytest.approx(1.0)
    assert data["summary"][name]["worst_bin"] in ld.SUMMARY_BINS
    assert f"| {name} | 2-5 m |" in md and "| network | " in md and "| oracle" in md
