#!/bin/bash
# validation of docs/history/rule_vo_init_pending_session22.md
# baseline: /work/main (VO code of the rule's parent); candidate: /work/wt22 (the candidate's code)
V=/tmp/s22/vinit
B="/work/main/.venv/bin/python -m metricslam_cli.main"
C="env PYTHONPATH=/work/wt22/shared:/work/wt22/cli:/work/wt22 /work/main/.venv/bin/python -m metricslam_cli.main"
both() {  # name seq [run flags]
  n=$1; q=$2; shift 2
  (cd /work/main && $B run $q --out $V/$n.base.txt --json $V/$n.base.json --deterministic --no-progress "$@" > $V/$n.base.log 2>&1) &
  (cd /work/wt22 && $C run $q --out $V/$n.cand.txt --json $V/$n.cand.json --deterministic --no-progress "$@" > $V/$n.cand.log 2>&1) &
  wait
}
D=/work/shared/data
both kitti06 $D/kitti_odometry/sequences/06          # learned scale, ATE SE(3)
both kitti01 $D/kitti_odometry/sequences/01
both raw0013 $D/kitti_raw_stereo/sequences/2011_09_26_drive_0013
for s in $(seq 131 150); do for size in 620x188 1241x376; do
  w=$V/worlds/loop_s${s}_$size
  [ -f $w/poses/00.txt ] || (cd /work/main && $B synth $w --frames 150 --seed $s --path loop --size $size > /dev/null 2>&1)
  both loop_s${s}_$size $w --no-scale
done; done
echo DONE > $V/DONE
