import json, os
D = "/tmp/s21/dv"
fails, ok_flagged, ok_n, rows = [], 0, 0, []
for sz in ("620x188", "1241x376"):
    for s in range(80, 100):
        n = f"loop_s{s}_{sz}"
        if not os.path.exists(f"{D}/{n}.eval.json"): continue
        e = json.load(open(f"{D}/{n}.eval.json")); st = json.load(open(f"{D}/{n}.json"))
        ate, k = e["ate_rmse_sim3_m"], st["vo_suspect_frames"]
        rows.append((n, round(ate, 3), k, st["vo_suspect_ranges"][:4]))
        if ate > 1: fails.append((n, ate, k))
        else: ok_n += 1; ok_flagged += k > 0
print("runs", len(rows), "failures", len(fails), "flagged failures", sum(f[2] > 0 for f in fails), fails)
print("non-failing runs flagged: %d of %d (%.0f %%)" % (ok_flagged, ok_n, 100 * ok_flagged / max(ok_n, 1)))
for k in ("kitti06", "kitti01", "raw0013"):
    p = f"{D}/{k}.json"
    if os.path.exists(p): print(k, "suspect frames", json.load(open(p))["vo_suspect_frames"])
for r in rows: print(*r)
