cd /work/main
run() {  # $1 tag, $2 extra args
for g in "15 22" "30 37" "51 51"; do echo "== k06 $g $1"; GAP_SRC=/tmp/k06full .venv/bin/python /work/exp/s18/gap.py $g $1 --preset kitti $2 2>&1 | grep -E "ATE|tracking loss" | grep -v INFO; done
for g in "40 47" "180 191" "260 269"; do echo "== loop300 $g $1"; .venv/bin/python /work/exp/s18/gap.py $g $1 $2 2>&1 | grep -E "ATE|tracking loss" | grep -v INFO; done
for g in "40 47" "90 99" "150 150"; do echo "== other150 $g $1"; GAP_SRC=/tmp/maps_bench17/other150 .venv/bin/python /work/exp/s18/gap.py $g $1 $2 2>&1 | grep -E "ATE|tracking loss" | grep -v INFO; done
}
run cand ""
run scaleonly "--config /tmp/scaleonly.yaml"
git show HEAD:shared/metricslam/slam/vo/local_vo.py > shared/metricslam/slam/vo/local_vo.py
run head ""
cp /tmp/lv_coast.py shared/metricslam/slam/vo/local_vo.py
