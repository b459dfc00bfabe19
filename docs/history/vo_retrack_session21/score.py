"""Score a re-track validation: python score.py [RUNS_DIR] [FIRST_SEED] (20 seeds from FIRST_SEED,
both sizes; RUNS_DIR holds base_*/cand_* runs and evals). Session 21: /tmp/s21/vv 60 (first form),
/tmp/s21/vv2 100 (second form, docs/history/vo_retrack2_session21/)."""
import json, statistics, glob, os, sys
V = sys.argv[1] if len(sys.argv) > 1 else "/tmp/s21/vv"
FIRST = int(sys.argv[2]) if len(sys.argv) > 2 else 60
def ev(v, n):
    p = f"{V}/{v}_{n}.eval.json"
    return json.load(open(p)) if os.path.exists(p) else None
rows = []
for sz in ("620x188", "1241x376"):
    for s in range(FIRST, FIRST + 20):
        n = f"loop_s{s}_{sz}"; b, c = ev("base", n), ev("cand", n)
        if b is None or c is None: continue
        st = json.load(open(f"{V}/cand_{n}.json"))
        rows.append((n, b["ate_rmse_sim3_m"], c["ate_rmse_sim3_m"], st["retracks"], st["retracks_kept"]))
fb = [r for r in rows if r[1] > 1]; fc = [r for r in rows if r[2] > 1]
new = [r for r in rows if r[2] > 1 and r[1] <= 1]
both = [r for r in rows if r[1] <= 1 and r[2] <= 1]
print("runs", len(rows), "failures base", len(fb), "cand", len(fc), "new failures", [r[0] for r in new])
if both:
    mb, mc = statistics.median(r[1] for r in both), statistics.median(r[2] for r in both)
    print("median ATE sim3 (neither fails): base %.3f cand %.3f (%+.1f %%)" % (mb, mc, 100 * (mc / mb - 1)))
for r in rows: print("%-20s base %7.3f cand %7.3f retracks %d kept %d" % r)
for k in ("kitti06", "kitti01", "raw0013"):
    b, c = ev("base", k), ev("cand", k)
    if b and c:
        st = json.load(open(f"{V}/cand_{k}.json"))
        print(k, "ATE SE3 base %.4f cand %.4f (%+.2f %%) retracks %d" % (b["ate_rmse_m"], c["ate_rmse_m"], 100 * (c["ate_rmse_m"] / b["ate_rmse_m"] - 1), st["retracks"]))
