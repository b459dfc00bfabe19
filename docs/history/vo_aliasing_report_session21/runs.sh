#!/bin/bash
cd /work/main; mkdir -p /tmp/s21/dv
for sz in 620x188 1241x376; do for s in $(seq 80 99); do d=loop_s${s}_${sz}
  .venv/bin/metricslam run /tmp/s21/voval2/$d --out /tmp/s21/dv/$d.txt --json /tmp/s21/dv/$d.json --deterministic --no-progress --no-scale >/dev/null 2>&1
  .venv/bin/metricslam eval --gt /tmp/s21/voval2/$d/poses/00.txt --est /tmp/s21/dv/$d.txt --json /tmp/s21/dv/$d.eval.json >/dev/null 2>&1
done; done
for k in kitti06=../shared/data/kitti_odometry/sequences/06 kitti01=../shared/data/kitti_odometry/sequences/01 raw0013=../shared/data/kitti_raw_stereo/sequences/2011_09_26_drive_0013; do
  n=${k%%=*}; seq=${k#*=}
  .venv/bin/metricslam run $seq --out /tmp/s21/dv/$n.txt --json /tmp/s21/dv/$n.json --deterministic --no-progress >/dev/null 2>&1
done
echo done
