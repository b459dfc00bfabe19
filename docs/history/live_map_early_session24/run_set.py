"""Run session 22's repro.py (../live_map_scale_session22) for each session of SESSIONS.json with the code at ROOT (PYTHONPATH): OUTDIR/<name>.<tag>.npz. usage: run_set.py SESSIONS.json ROOT TAG OUTDIR [NAME...]; THREADED=1 in the environment: the threaded back end at 10 Hz (--rate 10) instead of --rate 0 --deterministic"""
import json, os, subprocess, sys
from pathlib import Path
sessions_json, root, tag, outdir = sys.argv[1:5]
only = sys.argv[5:]
outdir = Path(outdir); outdir.mkdir(parents=True, exist_ok=True)
for s in json.loads(Path(sessions_json).read_text()):
    if only and s["name"] not in only: continue
    out = outdir / f"{s['name']}.{tag}.npz"
    if out.is_file(): continue
    env = dict(os.environ, PYTHONPATH=f"{root}/shared:{root}/cli:{root}:{root}/services/slam")
    cmd = ["/work/main/.venv/bin/python", str(Path(__file__).resolve().parent.parent / "live_map_scale_session22" / "repro.py"), str(out),
           *(["--rate", "10"] if os.environ.get("THREADED") else ["--rate", "0", "--deterministic"]),
           "--seq", s["seq"], "--map", s["map"], "--preset", s["preset"]] + (["--model", s["model"]] if s["model"] else [])
    r = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True)
    (outdir / f"{s['name']}.{tag}.log").write_text(r.stdout + r.stderr)
    print(s["name"], tag, r.returncode, r.stdout.strip().splitlines()[-1][:200] if r.stdout.strip() else r.stderr[-300:], flush=True)
