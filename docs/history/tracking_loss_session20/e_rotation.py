"""Scratch diagnostic of session 20 (not part of the project; paths are that session's work folder): rotation from the essential matrix between the last frame before a tracking loss and
the first frame of the new segment, against the truth and against the run's own link."""
import json, glob, os, re
import cv2, numpy as np
from metricslam.datasets import open_sequence
from metricslam.trajectory.io import read_kitti_poses
from metricslam.slam.loop.verification import match_descriptors

def rotdeg(R): return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
orb = cv2.ORB_create(nfeatures=1000, nlevels=4, fastThreshold=12)
for js in sorted(glob.glob('/tmp/s20/r2/*_coast.json')):
    name = os.path.basename(js).replace('_coast.json', '')
    seq_dir = js.replace('_coast.json', '')
    d = json.load(open(js)); interp = d['interpolated_frame_indices']
    if not interp: continue
    seq = open_sequence(seq_dir); gt = read_kitti_poses(f'{seq_dir}/poses/00.txt'); est = read_kitti_poses(js.replace('.json', '.txt'))
    runs = []
    for i in interp:
        if runs and i == runs[-1][-1] + 1: runs[-1].append(i)
        else: runs.append([i])
    for r in runs:
        a, b = r[0] - 1, r[-1] + 1
        if b >= len(seq): continue
        fa, fb = seq[a], seq[b]
        ga = cv2.cvtColor(fa.image, cv2.COLOR_BGR2GRAY) if fa.image.ndim == 3 else fa.image
        gb = cv2.cvtColor(fb.image, cv2.COLOR_BGR2GRAY) if fb.image.ndim == 3 else fb.image
        ka, da = orb.detectAndCompute(ga, None); kb, db = orb.detectAndCompute(gb, None)
        pairs = match_descriptors(db, da, 0.8)
        K = fa.camera.K
        ua = np.float64([ka[j].pt for j in pairs[:, 1]]); ub = np.float64([kb[j].pt for j in pairs[:, 0]])
        E, mask = cv2.findEssentialMat(ub, ua, K, method=cv2.RANSAC, prob=0.999, threshold=1.0)
        n_in = int(mask.sum()) if mask is not None else 0
        R_true = gt[a][:3, :3].T @ gt[b][:3, :3]
        R_run = est[a][:3, :3].T @ est[b][:3, :3]
        e_err = float('nan')
        if E is not None and E.shape == (3, 3) and n_in >= 8:
            _, R_b_a, t, _ = cv2.recoverPose(E, ub, ua, K, mask=mask)  # maps points of a's frame? (cam b from cam a)
            # recoverPose(E, points1=ub, points2=ua) gives R, t with x_a = R x_b + t  -> R = R_a_b
            e_err = rotdeg(R_b_a.T @ R_true) if rotdeg(R_b_a.T @ R_true) < rotdeg(R_b_a @ R_true) else rotdeg(R_b_a @ R_true)
        print(f"{name:22s} {a:3d}->{b:3d} turn {rotdeg(R_true):5.1f}  run link err {rotdeg(R_run.T @ R_true):5.2f}  E: pairs {len(pairs):3d} inl {n_in:3d} err {e_err:5.2f}")
