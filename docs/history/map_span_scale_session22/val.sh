#!/bin/bash
# validation of rule_map_span_scale_session22.md: seeds 121-130
cd /work/main
one() {  # seed cfg span
  s=$1; cfg=$2; sp=$3; w=/tmp/s22/val/s$s/${cfg}_$sp; mkdir -p $w
  ln -sfn /tmp/s22/val/s$s/loop300 $w/loop300; ln -sfn /tmp/s22/revg/other150 $w/other150
  if [ $cfg = ground ]; then fl="--scale-sources learned,ground --mount-height 1.65"; else fl=""; fi
  PYTHONPATH=. .venv/bin/python /work/exp/s22/revisit.py $w $s $sp $fl > $w/log.txt 2>&1
  grep RESULT $w/log.txt | sed "s/^RESULT /{\"cfg\": \"$cfg\", /; s/, {/, /" >> /tmp/s22/val/results.jsonl || echo "FAIL $s $cfg $sp" >> /tmp/s22/val/results.jsonl
}
for s in $(seq 121 130); do
  mkdir -p /tmp/s22/val/s$s
  PYTHONPATH=. .venv/bin/python -c "
from pathlib import Path; from metricslam.synth.scene import generate_sequence
generate_sequence(Path('/tmp/s22/val/s$s/loop300'), 300, seed=$s, size=(620, 188), path='loop')" > /dev/null 2>&1
  one $s learned inf & one $s learned 10 & wait
  one $s ground inf & one $s ground 10 & wait
done
echo DONE >> /tmp/s22/val/results.jsonl
