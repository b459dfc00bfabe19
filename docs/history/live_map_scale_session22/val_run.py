"""Run baseline (/work/main) and candidate (/work/wt22b) reproductions on every session of sessions.json."""
import json, os, subprocess
from pathlib import Path
V = Path("/tmp/s22/vlive")
ROOTS = {"base": "/work/main", "cand": "/work/wt22b"}
for s in json.loads((V / "sessions.json").read_text()):
    for tag, root in ROOTS.items():
        out = V / f"{s['name']}.{tag}.npz"
        if out.is_file():
            continue
        env = dict(os.environ, PYTHONPATH=f"{root}/shared:{root}/cli:{root}:{root}/services/slam")
        cmd = ["/work/main/.venv/bin/python", "/work/exp/s22/live/repro.py", str(out), "--rate", "0", "--deterministic",
               "--seq", s["seq"], "--map", s["map"], "--preset", s["preset"]] + (["--model", s["model"]] if s["model"] else [])
        r = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True)
        (V / f"{s['name']}.{tag}.log").write_text(r.stdout + r.stderr)
        print(s["name"], tag, r.returncode, r.stdout.strip().splitlines()[-1][:200] if r.stdout.strip() else r.stderr[-300:], flush=True)
