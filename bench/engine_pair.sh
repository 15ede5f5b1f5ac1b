#!/usr/bin/env bash
# Issue 39's end-to-end pair: the default engine (--engine auto, --precision auto) against
# `--engine torch --precision fp32`, full D3-Net (the bench's model: DenseNet-121, 20 classes, drawn heads),
# whole `aerialmtl predict` processes timed by farm-bench, A then B in turn, after one warm-up of each that
# fills OpenVINO's engine cache for the window shape (the cold compile is a once-per-shape cost, stated apart).
#
#   bash bench/engine_pair.sh OUTDIR SIZE T [native|avx2] [RUNS]
#
# avx2 caps both engines' kernels at AVX2 on this CPU (the emulation bench/RESULTS.md describes:
# ONEDNN_MAX_CPU_ISA, OV_CPU_MAX_ISA, ATEN_CPU_CAPABILITY; the bf16 probe empty). Prints farm-bench's report and
# each run's prediction.json stage timings (OUTDIR/a.log, b.log hold the commands' own output).
set -euo pipefail
out=$(realpath -m "$1"); size=$2; t=$3; isa=${4:-native}; runs=${5:-2}
mkdir -p "$out"
if [ "$isa" = avx2 ]; then
    export ONEDNN_MAX_CPU_ISA=AVX2 OV_CPU_MAX_ISA=AVX2 ATEN_CPU_CAPABILITY=avx2 AERIALMTL_CPU_BF16_FLAGS=
fi
export AERIALMTL_CACHE="$out/cache"
python - "$out" "$size" <<'EOF'
import sys
from pathlib import Path

from aerialmtl.formats.checkpoint import save_checkpoint
from aerialmtl.inference.cpu_bench import _synthetic_raster, bench_model

out, size = Path(sys.argv[1]), int(sys.argv[2])
if not (out / "full.pt").is_file():
    save_checkpoint(out / "full.pt", *bench_model("full"))
if not (out / f"r{size}.tif").is_file():
    _synthetic_raster(out / f"r{size}.tif", size)
EOF
a="aerialmtl predict $out/r$size.tif --model $out/full.pt --mc $t --quiet --overwrite --out $out/a"
b="aerialmtl predict $out/r$size.tif --model $out/full.pt --mc $t --quiet --overwrite --out $out/b --engine torch --precision fp32"
echo "# $(lscpu | sed -n 's/^Model name: *//p'), family $(lscpu | sed -n 's/^CPU family: *//p') model $(lscpu | sed -n 's/^Model: *//p'); isa $isa; ${size}² T=$t; load $(cut -d' ' -f1-3 /proc/loadavg)"
farm-bench -n "$runs" --warmup 1 --timeout 3600 --vs "sh -c 'exec $b >>$out/b.log 2>&1'" -- sh -c "exec $a >>$out/a.log 2>&1"
echo "# load after: $(cut -d' ' -f1-3 /proc/loadavg)"
for d in a b; do
    python -c "import json,sys; p=json.load(open(sys.argv[1])); print(sys.argv[2], p.get('engine'), p.get('precision'), {k: round(v, 1) for k, v in (p.get('timings_s') or p.get('timings') or {}).items() if isinstance(v, (int, float))})" "$out/$d/prediction.json" "$d"
done
