"""Rendered revisit (bench.maps.rendered_revisit) at a given seed, span threshold, run flags.
usage: revisit.py WORK SEED SPAN_M [run flags...]  -> prints one JSON line"""
import json, sys
from pathlib import Path
import numpy as np
import bench.maps as bm
import metricslam.slam.map.relocalizer as rl
from metricslam.synth.scene import generate_sequence
work, seed, span = Path(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3])
extra = sys.argv[4:]
rl.SPAN_SCALE_MIN_M = span
orig = bm.run
bm.run = lambda seq, out, *flags: orig(seq, out, *flags, *extra)
src = work / "loop300"
if not (src / "poses" / "00.txt").is_file():
    generate_sequence(src, 300, seed=seed, size=(620, 188), path="loop")
gen = bm.generate_sequence if hasattr(bm, "generate_sequence") else None
# skip the foreign-map part: reuse bench code but stub the other world with the same seed's map check off
import metricslam.synth.scene as sc
real_gen = sc.generate_sequence
r = None
try:
    r = bm.rendered_revisit(work)
except Exception as e:
    r = {"error": repr(e)}
r.update({"seed": seed, "span": span, "flags": " ".join(extra)})
if "session2_rmse_m" in r:
    r["session2_pct"] = 100 * r["session2_rmse_m"] / r["session2_path_m"]
print("RESULT " + json.dumps(r))
