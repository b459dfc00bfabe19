"""Apply the rule's decision to val*.py's outputs: score.py HEAD.jsonl CAND.jsonl [HEAD_BENCH.json CAND_BENCH.json [--third]]."""
import json, sys
import numpy as np


def load(p):
    return {r["name"]: r for r in map(json.loads, open(p).read().splitlines())}


h, c = load(sys.argv[1]), load(sys.argv[2])
worse = lambda a, b: b > 1.10 * a + 0.05  # noqa: E731
print("| scenario | HEAD ATE | cand ATE | ratio | cand post-gap mean | relocalized (cand) |")
print("| --- | --- | --- | --- | --- | --- |")
ok1, kid, harm, fails = True, [], [], []
for name, rc in c.items():
    rh = h[name]
    reloc = rc.get("relocalized_segments") or {}
    if rc["kind"] == "foreign" and reloc:
        ok1 = False
        fails.append(f"rule 1: {name} relocalized {reloc}")
    third = len(sys.argv) > 5 and sys.argv[5] == "--third"  # rule 3's amended rule 1 (see its file)
    worse_post = not third or rc.get("post_err_mean_m", 0) > rh.get("post_err_mean_m", 0) + 1.0
    if rc["kind"] != "foreign" and reloc and rc.get("post_err_mean_m", 0) >= 5.0 and worse_post:
        ok1 = False
        fails.append(f"rule 1: {name} post-gap {rc['post_err_mean_m']:.2f} m")
    if "ate_all_m" in rc:
        r = rc["ate_all_m"] / rh["ate_all_m"]
        (kid if rc["kind"] == "kidnap" else harm).append(r)
        if worse(rh["ate_all_m"], rc["ate_all_m"]):
            fails.append(f"rule {2 if rc['kind'] == 'kidnap' else 3}: {name} {rh['ate_all_m']:.2f} -> {rc['ate_all_m']:.2f} m")
        print(f"| {name} | {rh['ate_all_m']:.2f} m | {rc['ate_all_m']:.2f} m | {r:.2f} | {rc['post_err_mean_m']:.2f} m | {reloc} |")
    else:
        print(f"| {name} | - | - | - | - | {reloc} |")
if len(sys.argv) > 4:
    bh, bc = (json.load(open(p))["scenarios"] for p in sys.argv[3:5])
    for name in bh:
        a, b = bh[name]["coast"]["ate_se3_m"], bc[name]["coast"]["ate_se3_m"]
        harm.append(b / a)
        print(f"| bench: {name} | {a:.2f} m | {b:.2f} m | {b / a:.2f} | - | - |")
        if worse(a, b):
            fails.append(f"rule 3: bench {name} {a:.2f} -> {b:.2f} m")
med_k, med_h = float(np.median(kid)), float(np.median(harm))
if med_k >= 0.5:
    fails.append(f"rule 2: median kidnap ratio {med_k:.2f}")
if med_h > 1.02:
    fails.append(f"rule 3: median no-harm ratio {med_h:.3f}")
print(f"\nmedian kidnap ratio {med_k:.3f} over {len(kid)}; median no-harm ratio {med_h:.3f} over {len(harm)}")
print("ADOPT" if not fails else "NOT ADOPTED:\n" + "\n".join(fails))
