#!/bin/bash
# Issue 39: the command's share of the model-alone speed at 8192², T = 1, default engine (this CPU: OpenVINO bf16).
set -euo pipefail
cd "$(dirname "$0")/.."
out=$(realpath -m "$1")   # a folder bench/engine_pair.sh filled (full.pt); usage: bash bench/engine_share.sh OUT
export AERIALMTL_CACHE=$out/cache
echo "# load $(cut -d' ' -f1-3 /proc/loadavg) $(date -u +%T)"
aerialmtl bench --models full --cases openvino/bf16 --window 736 --windows 3 --size 0 2>&1 | tail -15
python - "$out" <<'P'
from pathlib import Path
from aerialmtl.inference.cpu_bench import _synthetic_raster
import sys
p = Path(sys.argv[1]) / "r8192.tif"
if not p.is_file():
    _synthetic_raster(p, 8192)
P
# (no warm-up: the run below includes OpenVINO's first compile of the plan's window shape)
echo "# 8192² T=1 $(date -u +%T) load $(cut -d' ' -f1-3 /proc/loadavg)"
/usr/bin/time -f "%e s wall %U user %S sys %M KB" aerialmtl predict $out/r8192.tif --model $out/full.pt --mc 1 --quiet --overwrite --out $out/p8192 2>&1 | tail -2
echo "# end $(date -u +%T) load $(cut -d' ' -f1-3 /proc/loadavg)"
python -c "import json; p=json.load(open('$out/p8192/prediction.json')); print(p['engine'], p['precision'], p['window_size'], p['windows_total'], p['overlap_factor'], {k: round(v,1) for k,v in p['timings_s'].items()})"
