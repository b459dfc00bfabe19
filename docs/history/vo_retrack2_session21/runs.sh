#!/bin/bash
cd /work/main; mkdir -p /tmp/s21/vv2
for v in base cand; do
  extra=(); [ $v = base ] && extra=(--config docs/history/vo_retrack2_session21/noretrack.yaml)
  for sz in 620x188 1241x376; do [ $sz = 1241x376 ] && until grep -q done /tmp/s21/gen_vo_val3.log; do sleep 5; done; for s in $(seq 100 119); do d=loop_s${s}_${sz}; until [ -f /tmp/s21/voval3/$d/poses/00.txt ]; do sleep 3; done
    .venv/bin/metricslam run /tmp/s21/voval3/$d --out /tmp/s21/vv2/${v}_$d.txt --json /tmp/s21/vv2/${v}_$d.json --deterministic --no-progress --no-scale "${extra[@]}" >/dev/null 2>&1
    .venv/bin/metricslam eval --gt /tmp/s21/voval3/$d/poses/00.txt --est /tmp/s21/vv2/${v}_$d.txt --json /tmp/s21/vv2/${v}_$d.eval.json >/dev/null 2>&1
  done; done
  for k in kitti06=../shared/data/kitti_odometry/sequences/06:../shared/data/kitti_odometry/poses/06.txt kitti01=../shared/data/kitti_odometry/sequences/01:../shared/data/kitti_odometry/poses/01.txt raw0013=../shared/data/kitti_raw_stereo/sequences/2011_09_26_drive_0013:../shared/data/kitti_raw_stereo/poses/2011_09_26_drive_0013.txt; do
    n=${k%%=*}; r=${k#*=}; seq=${r%%:*}; gt=${r#*:}
    .venv/bin/metricslam run $seq --out /tmp/s21/vv2/${v}_$n.txt --json /tmp/s21/vv2/${v}_$n.json --deterministic --no-progress "${extra[@]}" >/dev/null 2>&1
    .venv/bin/metricslam eval --gt $gt --est /tmp/s21/vv2/${v}_$n.txt --json /tmp/s21/vv2/${v}_$n.eval.json >/dev/null 2>&1
  done
done
echo done
