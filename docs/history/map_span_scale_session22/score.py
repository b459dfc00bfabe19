import json, sys, collections
rows = [json.loads(l) for l in open(sys.argv[1]) if l.startswith('{')]
by = collections.defaultdict(dict)
for r in rows: by[(r['seed'], r['cfg'])][r['span'] < 1e6] = r
for cfg in ('learned', 'ground'):
    print(f"## {cfg}\n| seed | baseline % | candidate % | diff | reloc b/c | foreign b/c | S scale cand |\n|---|---|---|---|---|---|---|")
    b_all, c_all, worst = [], [], -9
    for (seed, c), d in sorted(by.items()):
        if c != cfg: continue
        b, n = d[False], d[True]
        pb, pn = b.get('session2_pct'), n.get('session2_pct')
        if pb is not None and pn is not None:
            b_all.append(pb); c_all.append(pn); worst = max(worst, pn - pb)
        print(f"| {seed} | {pb:.3f} | {pn:.3f} | {pn-pb:+.3f} | {b['relocalized']}/{n['relocalized']} | "
              f"{b['foreign_map']['relocalized']}/{n['foreign_map']['relocalized']} | {n['scale_map_per_session']:.4f} |")
    print(f"mean baseline {sum(b_all)/len(b_all):.3f} %, candidate {sum(c_all)/len(c_all):.3f} % (n={len(b_all)}); worst increase {worst:+.3f} points\n")
