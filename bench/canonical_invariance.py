"""Does the depth network read the same metric depth whatever the camera? (issue #17 item 2)

Contract version 2 (``metricslam.depth.canonical``) warps every image to one canonical camera, so
a crop or a rescale of a frame should change nothing but the field of view. Per model:

A. **Crops and rescales of real frames** (every ``--step``-th frame of each ``--seq``): the full
   frame's inverse-depth map (``predict_inv_depth(image, camera=camera)``), then centre crops
   keeping 1/2 and 2/3 of the width (full height; ``cx`` shifts by the crop's left edge) and
   rescales by 0.5x and 2x (``PinholeCamera.resized``). For every valid cell of a variant's grid,
   its centre is mapped to the full image's pixel on the same ray and the full map is sampled
   there (:mod:`bench.canonical_variants`): median of ``depth_variant / depth_full`` (target
   within ±3 %), its IQR, and the fraction of the variant's cells that are valid. Version-1 maps
   have no NaN (all cells valid); they are expected to fail the crops (the "before" row).
B. **Rendered streets at four focal lengths and three aspect ratios** (``metricslam synth``,
   exact depth): per (fx, aspect), median over valid cells and frames of ``depth_net /
   depth_exact``, the exact depth being the per-cell median of ``depth_0`` on the model's output
   grid over the image (target within ±10 %), and the fraction of valid cells. Renders are cached
   under ``--render-dir`` (reused when complete).

``--shipped-as-v2`` adds (and writes, if absent) the shipped float32 network with its metadata
rewritten to contract version 2 (canonical camera = KITTI 00's at the 512x256 input), without any
field-of-view training: a baseline for what the v2 plumbing alone does.

Example::

    nice -n 15 .venv/bin/python -m bench.canonical_invariance \\
        --model shared/metricslam/models/depth_l3.onnx --shipped-as-v2 \\
        --seq ../shared/data/kitti_raw_stereo/sequences/2011_09_26_drive_0013 \\
        --seq ../shared/data/kitti_odometry/sequences/06 --out bench/results/canonical_invariance
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from bench.canonical_variants import (
    VARIANT_SPECS,
    depth_ratios,
    exact_depth_cells,
    make_variants,
    net_over_exact,
    ratio_stats,
)
from bench.machine import command_line, publish
from metricslam.datasets import open_sequence
from metricslam.depth import FLOAT32_MODEL_PATH, DepthModel, ModelContract

RUN_DIR = Path("runs/canonical_invariance")
SHIPPED_AS_V2 = RUN_DIR / "shipped_as_v2.onnx"
#: KITTI odometry 00's camera (718.856 px at 1241x376) at the shipped 512x256 input
KITTI_CANONICAL_FX_PX = 718.856 * 512 / 1241
KITTI_CANONICAL_FY_PX = 718.856 * 256 / 376
FOCALS_PX = (400.0, 700.0, 1000.0, 1400.0)
#: aspect label -> rendered size (W, H)
SIZES = {"4:3": (640, 480), "16:9": (854, 480), "3.3:1": (1241, 376)}
#: world seeds of the renders: < 1000 like the SLAM test streets, none of the depth training's
SEEDS = (701, 702, 703)
TARGET_A = 0.03
TARGET_B = 0.10
METRICSLAM = [sys.executable, "-m", "metricslam_cli.main"]


def write_metadata_as_v2(src: str | Path, dst: str | Path, fx_px: float = KITTI_CANONICAL_FX_PX,
                         fy_px: float = KITTI_CANONICAL_FY_PX, valid_min_fraction: float = 0.75) -> Path:
    """Copy the ONNX model ``src`` to ``dst`` with its contract rewritten to version 2 (the graph
    and every other metadata key unchanged)."""
    import onnx

    model = onnx.load(str(src))
    meta = {p.key: p.value for p in model.metadata_props}
    old = ModelContract.from_metadata(meta)
    new = ModelContract(**{**old.model_dump(), "contract_version": "2", "canonical_fx_px": float(fx_px),
                           "canonical_fy_px": float(fy_px), "valid_min_fraction": float(valid_min_fraction)})
    meta.update(new.to_metadata())
    del model.metadata_props[:]
    for key, value in meta.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(dst))
    return dst


# ----- part A: crops and rescales of real frames -----

def part_a_frame(model: DepthModel, image: np.ndarray, camera, variants) -> dict[str, tuple[np.ndarray, float]]:
    """Ratios and valid fraction of each variant of one frame (plus the full frame's valid fraction)."""
    full = model.predict_inv_depth(image, camera=camera).inv_depth_per_m
    out = {"full": (np.array([]), float(np.isfinite(full).mean()))}
    for var in variants:
        inv = model.predict_inv_depth(var.image, camera=var.camera).inv_depth_per_m
        out[var.name] = depth_ratios(full, camera, inv, var.camera)
    return out


def part_a(models: dict[str, DepthModel], seq_dirs: list[str], step: int) -> dict:
    """``{label: {seq_name | "all": {variant: stats + valid_fraction}}}`` (module docstring, A)."""
    names = ["full"] + [name for name, _, _ in VARIANT_SPECS]
    pools = {label: {} for label in models}
    for seq_dir in seq_dirs:
        seq = open_sequence(seq_dir)
        seq_name = Path(seq_dir).name
        for i in range(0, len(seq), step):
            frame = seq[i]
            variants = make_variants(frame.image, frame.camera)
            for label, model in models.items():
                per = part_a_frame(model, frame.image, frame.camera, variants)
                for key in (seq_name, "all"):
                    pool = pools[label].setdefault(key, {n: ([], []) for n in names})
                    for name, (ratios, valid) in per.items():
                        pool[name][0].append(ratios)
                        pool[name][1].append(valid)
    out = {}
    for label, by_seq in pools.items():
        out[label] = {}
        for key in [k for k in by_seq if k != "all"] + ["all"]:  # the pooled row last
            pool = by_seq[key]
            out[label][key] = {}
            for name, (ratios, valids) in pool.items():
                stats = ratio_stats(np.concatenate(ratios)) if name != "full" else {}
                out[label][key][name] = {**stats, "valid_fraction": float(np.mean(valids)), "frames": len(valids)}
    return out


# ----- part B: rendered streets at several focal lengths and aspect ratios -----

def render(fx_px: float, size: tuple[int, int], seed: int, frames: int, render_dir: Path) -> Path:
    """The cached render ``render_dir/fx{fx}_{W}x{H}_s{seed}`` (``metricslam synth``, written to a
    temporary folder first so an interrupted render is never reused)."""
    folder = render_dir / f"fx{fx_px:g}_{size[0]}x{size[1]}_s{seed}"
    if (folder / "depth_0").is_dir() and len(list((folder / "depth_0").glob("*.png"))) >= frames:
        return folder
    tmp = folder.with_name(folder.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.parent.mkdir(parents=True, exist_ok=True)
    cmd = METRICSLAM + ["synth", str(tmp), "--frames", str(frames), "--seed", str(seed),
                        "--size", f"{size[0]}x{size[1]}", "--fx", f"{fx_px:g}", "--no-progress"]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    shutil.rmtree(folder, ignore_errors=True)
    os.replace(tmp, folder)
    return folder


def part_b(models: dict[str, DepthModel], focals: tuple[float, ...], seeds: tuple[int, ...], frames: int,
           render_dir: Path) -> dict:
    """``{label: [row per (fx, aspect)]}`` (module docstring, B)."""
    out: dict[str, list] = {label: [] for label in models}
    for fx in focals:
        for aspect, size in SIZES.items():
            pooled = {label: ([], [], {}) for label in models}
            for seed in seeds:
                seq = open_sequence(render(fx, size, seed, frames, render_dir))
                for i in range(len(seq)):
                    frame = seq[i]
                    for label, model in models.items():
                        inv = model.predict_inv_depth(frame.image, camera=frame.camera).inv_depth_per_m
                        exact = exact_depth_cells(frame.depth_m, inv.shape)
                        ratios, valid = net_over_exact(inv, exact)
                        pooled[label][0].append(ratios)
                        pooled[label][1].append(valid)
                        pooled[label][2].setdefault(seed, []).append(ratios)
            for label, (ratios, valids, per_seed) in pooled.items():
                seed_medians = {s: ratio_stats(np.concatenate(r))["median"] for s, r in per_seed.items()}
                out[label].append({"fx_px": fx, "aspect": aspect, "size": f"{size[0]}x{size[1]}",
                                   **ratio_stats(np.concatenate(ratios)),
                                   "valid_fraction": float(np.mean(valids)), "frames": len(valids),
                                   "median_per_seed": seed_medians})
    return out


# ----- report -----

def _within(median: float | None, target: float) -> bool:
    return median is not None and abs(median - 1.0) <= target


def verdicts(result: dict) -> dict:
    """Per model: A passes when every variant on every sequence is within ±3 %; B when every
    (fx, aspect) is within ±10 %."""
    out = {}
    for label, res in result["models"].items():
        a_rows = [stats for key, per in res["part_a"].items() if key != "all"
                  for name, stats in per.items() if name != "full"]
        out[label] = {"part_a": bool(a_rows) and all(_within(r["median"], TARGET_A) for r in a_rows),
                      "part_b": bool(res["part_b"]) and all(_within(r["median"], TARGET_B) for r in res["part_b"])}
    return out


def _ratio(x: float | None) -> str:
    return "–" if x is None else f"×{x:.3f}"


def _mark(x: float | None, target: float) -> str:
    return "yes" if _within(x, target) else "**no**"


def markdown(result: dict, command: str, machine: str) -> str:
    load = max(result["load_average_start"][0], result["load_average_end"][0])
    lines = ["# Canonical-camera invariance of the depth network (bench/canonical_invariance.py)", "",
             f"Command: `{command}`  ", f"Machine: {machine}  ",
             f"Load average (1 min) at start / end: {result['load_average_start'][0]:.2f} / "
             f"{result['load_average_end'][0]:.2f}; wall {result['wall_s']:.0f} s for all models"
             + (" — above 2: the machine may have been shared with training (timings only; the "
                "ratios do not depend on it)." if load > 2 else "."), "",
             "## Summary", "",
             "| model | contract | A: worst \\|median − 1\\| over crops/rescales, per sequence (target 3 %) | A pass "
             "| B: worst \\|median − 1\\| over fx × aspect (target 10 %) | B pass |",
             "| --- | --- | --- | --- | --- | --- |"]
    for label, res in result["models"].items():
        a = [s["median"] for k, per in res["part_a"].items() if k != "all" for n, s in per.items() if n != "full"]
        b = [r["median"] for r in res["part_b"]]
        worst_a = max((abs(m - 1) for m in a if m is not None), default=None)
        worst_b = max((abs(m - 1) for m in b if m is not None), default=None)
        v = result["verdicts"][label]
        lines.append(f"| {label} | v{res['contract_version']} | "
                     + ("–" if worst_a is None else f"{100 * worst_a:.1f} %") + f" | {'yes' if v['part_a'] else '**no**'} | "
                     + ("–" if worst_b is None else f"{100 * worst_b:.1f} %") + f" | {'yes' if v['part_b'] else '**no**'} |")
    lines += ["", "Part A: median of depth_variant / depth_full over the variant's valid cells (pooled over "
              f"every {result['step']}th frame), IQR, and the share of the variant's cells that are valid; "
              "A passes when every variant's median on every sequence is within ±3 % (the pooled row 'all' "
              "is shown, not used). "
              "Part B: median of depth_net / depth_exact over valid cells of "
              f"{result['frames']} frames x seeds {result['seeds']} per render; exact depth = per-cell median of "
              "depth_0 (cells at least half covered); B passes when every (fx, aspect) is within ±10 %.", ""]
    for label, res in result["models"].items():
        lines += [f"## {label}", "", f"`{res['path']}`, model_id `{res['model_id']}`, contract version "
                  f"{res['contract_version']}" + (f", canonical fx/fy {res['canonical_fx_px']:.2f}/"
                                                  f"{res['canonical_fy_px']:.2f} px, valid_min_fraction "
                                                  f"{res['valid_min_fraction']}" if res["contract_version"] == "2"
                                                  else "") + ".", "",
                  "### A. Crops and rescales of real frames", "",
                  "| sequence | variant | median ratio | IQR | valid cells | within ±3 % |", "| --- | --- | --- | --- | --- | --- |"]
        for key, per in res["part_a"].items():
            for name, s in per.items():
                if name == "full":
                    lines.append(f"| {key} | full frame ({s['frames']} frames) | – | – | "
                                 f"{100 * s['valid_fraction']:.1f} % | – |")
                    continue
                lines.append(f"| {key} | {name} | {_ratio(s['median'])} | "
                             + ("–" if s["iqr"] is None else f"{s['iqr']:.3f}")
                             + f" | {100 * s['valid_fraction']:.1f} % | {_mark(s['median'], TARGET_A)} |")
        lines += ["", "### B. Rendered streets, exact depth", "",
                  "| fx (px) | aspect | size | median net/exact | IQR | valid cells | per seed | within ±10 % |",
                  "| --- | --- | --- | --- | --- | --- | --- | --- |"]
        for r in res["part_b"]:
            seeds = " ".join(_ratio(m) for m in r["median_per_seed"].values())
            lines.append(f"| {r['fx_px']:g} | {r['aspect']} | {r['size']} | {_ratio(r['median'])} | "
                         + ("–" if r["iqr"] is None else f"{r['iqr']:.3f}")
                         + f" | {100 * r['valid_fraction']:.1f} % | {seeds} | {_mark(r['median'], TARGET_B)} |")
        lines.append("")
    return "\n".join(lines) + "\n"


def evaluate(model_paths: list[str], seq_dirs: list[str], step: int, focals: tuple[float, ...],
             seeds: tuple[int, ...], frames: int, render_dir: Path) -> dict:
    """Parts A and B for every model (JSON-ready)."""
    load_start = list(os.getloadavg())
    models, info = {}, {}
    for path in model_paths:
        label = Path(path).stem if Path(path).stem not in models else str(path)
        models[label] = DepthModel.load(path)
        c = models[label].contract
        info[label] = {"path": str(path), "model_id": c.model_id, "contract_version": c.contract_version,
                       "canonical_fx_px": c.canonical_fx_px, "canonical_fy_px": c.canonical_fy_px,
                       "valid_min_fraction": c.valid_min_fraction}
    t0 = time.perf_counter()
    a = part_a(models, seq_dirs, step) if seq_dirs else {label: {} for label in models}
    b = part_b(models, focals, seeds, frames, render_dir) if focals else {label: [] for label in models}
    wall = time.perf_counter() - t0
    result = {"sequences": seq_dirs, "step": step, "focals_px": list(focals), "sizes": SIZES, "seeds": list(seeds),
              "frames": frames, "render_dir": str(render_dir), "wall_s": wall, "targets": {"part_a": TARGET_A, "part_b": TARGET_B},
              "models": {label: {**info[label], "part_a": a[label], "part_b": b[label]}
                         for label in models},
              "load_average_start": load_start, "load_average_end": list(os.getloadavg())}
    result["verdicts"] = verdicts(result)
    return result


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", action="append", default=[], help="ONNX depth model (repeat)")
    p.add_argument("--shipped-as-v2", action="store_true",
                   help=f"also the shipped float32 network relabelled contract v2 ({SHIPPED_AS_V2}, written if absent)")
    p.add_argument("--seq", action="append", default=[], help="KITTI-layout folder for part A (repeat)")
    p.add_argument("--step", type=int, default=10, help="part A: every STEP-th frame (default 10)")
    p.add_argument("--fx", type=float, nargs="*", default=list(FOCALS_PX), help="part B focal lengths, px (none: skip B)")
    p.add_argument("--seeds", type=int, nargs="+", default=list(SEEDS), help="part B world seeds")
    p.add_argument("--frames", type=int, default=3, help="part B frames per render (default 3)")
    p.add_argument("--render-dir", type=Path, default=RUN_DIR / "renders", help="part B render cache")
    p.add_argument("--out", metavar="PREFIX", help="write PREFIX.json and PREFIX.md")
    args = p.parse_args(argv)
    models = list(args.model)
    if args.shipped_as_v2:
        if not SHIPPED_AS_V2.is_file():
            write_metadata_as_v2(FLOAT32_MODEL_PATH, SHIPPED_AS_V2)
        models.append(str(SHIPPED_AS_V2))
    if not models:
        p.error("name at least one --model (or --shipped-as-v2)")
    cv2.setNumThreads(1)
    command = command_line("bench.canonical_invariance", argv)
    result = evaluate(models, args.seq, args.step, tuple(args.fx), tuple(args.seeds), args.frames, args.render_dir)
    publish(args.out, result, command, markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
