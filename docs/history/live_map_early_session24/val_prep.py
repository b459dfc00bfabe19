"""Validation sessions of rule_live_map_early_session24.md (session-1 maps at HEAD, session-2 folders)."""
import json, sys
from pathlib import Path
sys.path.insert(0, "/work/main")
from bench.maps import cut, run, RENDERED  # cut: PNG or JPEG (raw 1405)
from metricslam.synth.scene import generate_sequence
V = Path("/tmp/s24/val"); V.mkdir(parents=True, exist_ok=True); D = Path("/work/shared/data")
sessions = []
def real(name, mapname, src, m_start, m_stop, s_start, s_stop):
    s1 = cut(src, V / f"{mapname}_s1", m_start, m_stop)
    if not (V / f"{mapname}_map").is_dir():
        print(run(s1, V / f"{mapname}_s1.txt", "--preset", "kitti", "--save-map", str(V / f"{mapname}_map"))[0], mapname, flush=True)
    s2 = cut(src, V / f"{name}_s2", s_start, s_stop)
    sessions.append(dict(name=name, kind="real", seq=str(s2), map=str(V / f"{mapname}_map"), preset="kitti",
                         model=None, s1=str(V / f"{mapname}_s1.txt"), offset=s_start - m_start))
o = D / "kitti_odometry/sequences"; r = D / "kitti_raw_stereo/sequences"
real("k01_10", "k01", o / "01", 0, 51, 10, 51)
real("k01_20", "k01", o / "01", 0, 51, 20, 51)
real("k06_30", "k06", o / "06", 0, 51, 30, 51)
real("r0001_25", "r0001", r / "2011_09_26_drive_0001", 0, 54, 25, 54)
real("r1405_35", "r1405", r / "2011_09_26_residential_1405", 0, 80, 35, 80)
real("r0013_30", "r0013", r / "2011_09_26_drive_0013", 60, 144, 30, 111)
for seed in range(235, 241):
    src = V / f"loop_s{seed}"
    if not (src / "poses/00.txt").is_file():
        generate_sequence(src, 300, seed=seed, size=(620, 188), path="loop")
    s1, s2 = cut(src, V / f"rs{seed}_s1", 0, 150), cut(src, V / f"rs{seed}_s2", 190, 300)
    if not (V / f"rs{seed}_map").is_dir():
        print(run(s1, V / f"rs{seed}_s1.txt", "--save-map", str(V / f"rs{seed}_map"), "--model", RENDERED)[0], seed, flush=True)
    sessions.append(dict(name=f"rs{seed}", kind="rendered", seq=str(s2), map=str(V / f"rs{seed}_map"), preset="synth",
                         model=RENDERED, s1=str(V / f"rs{seed}_s1.txt"), offset=190, truth=str(src / "poses/00.txt")))
(V / "sessions.json").write_text(json.dumps(sessions, indent=1))
print(len(sessions), "sessions")
