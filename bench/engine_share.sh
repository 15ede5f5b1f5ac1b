#!/bin/bash
# Issue 39 (as run for bench/RESULTS.md, paths of that session): the command's share of the model-alone speed at 8192², T = 1, default engine (this CPU: OpenVINO bf16).
source /work/venv/bin/activate
cd /work/main
out=/work/runs/pair_native_t8
export AERIALMTL_CACHE=$out/cache
echo "# load $(cut -d' ' -f1-3 /proc/loadavg) $(date -u +%T)"
aerialmtl bench --models full --cases openvino/bf16 --window 736 --windows 3 --size 0 2>&1 | tail -15
python - <<'P'
from pathlib import Path
from aerialmtl.inference.cpu_bench import _synthetic_raster
p = Path("/work/runs/pair_native_t8/r8192.tif")
if not p.is_file():
    _synthetic_raster(p, 8192)
P
echo "# warm-up (one window) $(date -u +%T) load $(cut -d' ' -f1-3 /proc/loadavg)"
python - <<'P'
import json
# an AOI of one window in the corner: fills the engine cache for the plan's window shape
aoi = {"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {}, "geometry": {"type": "Polygon",
       "coordinates": [[[500000, 5000000], [500300, 5000000], [500300, 4999700], [500000, 4999700], [500000, 5000000]]]}}]}
json.dump(aoi, open("/work/runs/pair_native_t8/corner.geojson", "w"))
P
/usr/bin/time -f "%e s wall %U user %S sys %M KB" aerialmtl predict $out/r8192.tif --model $out/full.pt --mc 1 --quiet --overwrite --out $out/w8192 --aoi $out/corner.geojson 2>&1 | tail -2
echo "# 8192² T=1 $(date -u +%T) load $(cut -d' ' -f1-3 /proc/loadavg)"
/usr/bin/time -f "%e s wall %U user %S sys %M KB" aerialmtl predict $out/r8192.tif --model $out/full.pt --mc 1 --quiet --overwrite --out $out/p8192 2>&1 | tail -2
echo "# end $(date -u +%T) load $(cut -d' ' -f1-3 /proc/loadavg)"
python -c "import json; p=json.load(open('$out/p8192/prediction.json')); print(p['engine'], p['precision'], p['window_size'], p['windows_total'], p['overlap_factor'], {k: round(v,1) for k,v in p['timings_s'].items()})"
