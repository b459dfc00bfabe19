"""Prepare the validation sessions of rule_live_map_scale_session22.md (session-1 maps, session-2 folders)."""
import json
from pathlib import Path
import shutil
from bench.maps import cut as cut_png, run, RENDERED


def cut(src, dst, start, stop):
    """bench.maps.cut, for any image extension (raw 1405 is JPEG)."""
    if (src / "image_0" / "000000.png").is_file():
        return cut_png(src, dst, start, stop)
    dst.mkdir(parents=True, exist_ok=True)
    shutil.copy(src / "calib.txt", dst / "calib.txt")
    for sub in ("image_0", "image_1"):
        (dst / sub).mkdir(exist_ok=True)
        for j, i in enumerate(range(start, stop)):
            shutil.copy(src / sub / f"{i:06d}.jpg", dst / sub / f"{j:06d}.jpg")
    times = (src / "times.txt").read_text().split()
    (dst / "times.txt").write_text("".join(f"{times[i]}\n" for i in range(start, stop)))
    return dst
from metricslam.synth.scene import generate_sequence
V = Path("/tmp/s22/vlive"); D = Path("/work/shared/data")
K = ("--preset", "kitti")
sessions = []
def real(name, src, m_stop, s_start, s_stop):
    s1 = cut(src, V / f"{name}_s1", 0, m_stop)
    if not (V / f"{name}_map").is_dir():
        run(s1, V / f"{name}_s1.txt", *K, "--save-map", str(V / f"{name}_map"))
    s2 = cut(src, V / f"{name}_s2", s_start, s_stop)
    sessions.append(dict(name=name, kind="real", seq=str(s2), map=str(V / f"{name}_map"), preset="kitti",
                         model=None, s1=str(V / f"{name}_s1.txt"), offset=s_start))
o6 = D / "kitti_odometry/sequences/06"
real("k06_10", o6, 51, 10, 51)
sessions.append(dict(sessions[-1], name="k06_20", seq=str(cut(o6, V / "k06_20_s2", 20, 51)), offset=20))
real("r0001", D / "kitti_raw_stereo/sequences/2011_09_26_drive_0001", 40, 15, 54)
real("r1405", D / "kitti_raw_stereo/sequences/2011_09_26_residential_1405", 60, 20, 80)
for seed in (151, 152, 153, 154):
    src = V / f"loop_s{seed}"
    if not (src / "poses/00.txt").is_file():
        generate_sequence(src, 300, seed=seed, size=(620, 188), path="loop")
    s1, s2 = cut(src, V / f"rs{seed}_s1", 0, 150), cut(src, V / f"rs{seed}_s2", 190, 300)
    if not (V / f"rs{seed}_map").is_dir():
        run(s1, V / f"rs{seed}_s1.txt", "--save-map", str(V / f"rs{seed}_map"), "--model", RENDERED)
    sessions.append(dict(name=f"rs{seed}", kind="rendered", seq=str(s2), map=str(V / f"rs{seed}_map"), preset="synth",
                         model=RENDERED, s1=str(V / f"rs{seed}_s1.txt"), offset=190, truth=str(src / "poses/00.txt")))
(V / "sessions.json").write_text(json.dumps(sessions, indent=1))
print(len(sessions), "sessions")
