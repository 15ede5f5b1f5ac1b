#!/usr/bin/env bash
# One GPU check, at most ~8 minutes, one results file (default bench/gpu-results.txt, or $1).
#
# Measures on the first CUDA GPU what issues 11-19 asked for:
#   1. predict, full D3-Net (DenseNet-121, 20 classes, untrained), 8192² synthetic orthophoto, through the CLI,
#      T = 1 and T = 30, end to end (wall time, prediction.json stage timings) against the model alone
#      (bench/predict.py --speed on 2048², its model-only Mpx/s); each predict also prints issue 46's ratios:
#      end-to-end Mpx/s (target >= 50 at T = 1) and end to end over its own model stage (model / total: target
#      >= 0.7 at T = 1, >= 0.85 at T = 30), and the COG's share of the total;
#   2. training: the real training loop (bench/train_loop.py: `aerialmtl train`'s library call, the paper config,
#      batch 8, on a synthetic town tiled 320/160) — its samples/s, the model step alone at the same batch and
#      precision, the GPU's busy share (nvidia-smi every 250 ms, over the training steps), memory, and the
#      seconds of validation and calibration; and the model step under torch.compile (bench/train.py --compile);
#   3. a job of four 4096² inputs at T = 1 with each input's COGs built after its strip (as on a CPU) and in a
#      thread beside the next input's strip (the default on a GPU), in turn: the job's Mpx/s;
#   4. the GPU, driver, torch version and the load of the machine next to every number.
# Each step has its own time limit so that the whole script ends within ~8 minutes; a step that runs out
# of time is recorded as such. Run from the repository root: `bash bench/gpu.sh`.
set -u
cd "$(dirname "$0")/.."
OUT="${1:-bench/gpu-results.txt}"
TMP="$(mktemp -d)"
trap 'rm -rf "$TMP"' EXIT
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
PY="${PYTHON:-python}"

step() {  # step LIMIT_S TITLE COMMAND...
  local limit="$1" title="$2"; shift 2
  {
    echo "## $title"
    echo "command: $*"
    echo "load before: $(cut -d' ' -f1-3 /proc/loadavg)"
  } >>"$OUT"
  local t0=$SECONDS
  timeout "$limit" bash -c '"$@"' bash "$@" >>"$OUT" 2>"$TMP/err"
  local rc=$?
  if [ $rc -eq 124 ]; then echo "TIMED OUT after ${limit}s" >>"$OUT"; fi
  if [ $rc -ne 0 ] && [ $rc -ne 124 ]; then echo "FAILED (exit $rc): $(tail -c 1500 "$TMP/err")" >>"$OUT"; fi
  echo "wall: $((SECONDS - t0)) s; load after: $(cut -d' ' -f1-3 /proc/loadavg)" >>"$OUT"
  echo >>"$OUT"
}

{
  echo "# aerialmtl GPU check, $(date -u '+%Y-%m-%d %H:%M UTC'), git $(git rev-parse --short HEAD 2>/dev/null)"
  nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>/dev/null || echo "nvidia-smi: none"
  "$PY" -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'gpu', torch.cuda.is_available() and torch.cuda.get_device_name(0))"
  echo "CPU: $(lscpu | sed -n 's/^Model name: *//p' | head -1), $(nproc) cores"
  echo
} >"$OUT"

# A full-model checkpoint and an 8192² orthophoto (written block by block).
"$PY" - "$TMP" <<'EOF'
import sys
from pathlib import Path
sys.path.insert(0, "bench")
from predict import make_model, synthetic_raster
from aerialmtl.formats.checkpoint import save_checkpoint
tmp = Path(sys.argv[1])
model, meta = make_model("full")
save_checkpoint(tmp / "full.pt", model, meta)
synthetic_raster(tmp / "ortho8192.tif", 8192, 8192)
for i in range(4):
    synthetic_raster(tmp / f"many{i}.tif", 4096, 4096)
EOF

predict_case() {  # T: one predict of the 8192² orthophoto; prints its stage timings and issue 46's ratios
  local t0; t0=$(date +%s%N)
  "$PY" -m aerialmtl predict "$TMP/ortho8192.tif" --model "$TMP/full.pt" --out "$TMP/pred$1" --mc "$1" \
    --device cuda --quiet --overwrite || return $?
  local wall_ns=$(( $(date +%s%N) - t0 ))
  "$PY" - "$TMP/pred$1/prediction.json" "$wall_ns" <<'PYEOF'
import json, sys
i = json.load(open(sys.argv[1]))
t = i.get("timings_s") or {}
mpx = i["grid"]["width"] * i["grid"]["height"] / 1e6
total, model = t.get("total") or float("nan"), t.get("model") or float("nan")
wall = int(sys.argv[2]) / 1e9
print(json.dumps({k: i.get(k) for k in ("engine", "precision", "batch_size", "window_size", "overlap_factor",
                                        "mc_samples", "timings_s")}))
# issue 46's targets: T = 1 >= 50 Mpx/s end to end and >= 0.7x its model stage; T = 30 >= 0.85x its model stage
print(json.dumps({"output_mpx": mpx, "end_to_end_mpx_per_s": round(mpx / total, 2),
                  "whole_process_mpx_per_s": round(mpx / wall, 2), "wall_s": round(wall, 2),
                  "model_stage_mpx_per_s": round(mpx / model, 2),
                  "end_to_end_vs_model_stage": round(model / total, 3),
                  "cog_share_of_total": round((t.get("cog") or 0.0) / total, 3)}))
PYEOF
}

many_case() {  # four 4096² inputs, T = 1, in one job: commits inline (as on a CPU) and beside the next strip, in turn
  "$PY" - "$TMP" <<'PYEOF'
import json, sys, time
from pathlib import Path
from aerialmtl.inference import jobs
tmp = Path(sys.argv[1])
srcs = [tmp / f"many{i}.tif" for i in range(4)]
for in_thread in (False, True, False, True):  # the first pays CUDA's start
    jobs.commits_in_thread = lambda device, v=in_thread: v
    t0 = time.perf_counter()
    res = jobs.predict_many(srcs, tmp / "full.pt", tmp / "many_out", device="cuda", mc=1, overwrite=True,
                            progress=False)
    wall = time.perf_counter() - t0
    mpx = sum(r.grid.width * r.grid.height for r in res.results) / 1e6
    print(json.dumps({"commit_in_thread": in_thread, "inputs": len(res.results), "wall_s": round(wall, 2),
                      "job_mpx_per_s": round(mpx / wall, 2),
                      "per_input_strip_s": [round(r.timings.get("strip_total", 0.0), 2) for r in res.results],
                      "per_input_cog_s": [round(r.timings.get("cog", 0.0), 2) for r in res.results]}), flush=True)
PYEOF
}

export -f predict_case many_case
export TMP PY
step 60 "model alone: full D3-Net, 2048², T=1 (bench/predict.py --speed, precision auto)" \
  "$PY" bench/predict.py --speed --size 2048 --precisions auto --tmp "$TMP"
step 60 "predict 8192², T=1, end to end (CLI, --device cuda, defaults)" predict_case 1
step 100 "predict 8192², T=30, end to end (CLI, --device cuda, defaults)" predict_case 30
step 60 "predict 4 inputs of 4096², T=1, one job: COGs inline vs beside the next strip (issue 46)" many_case
step 140 "train loop vs model step alone, GPU busy share, memory (bench/train_loop.py, paper config, batch 8)" \
  "$PY" bench/train_loop.py --device cuda --town 2048 --steps 200 --workdir "$TMP/trainloop"
step 40 "train model step, torch.compile: samples/s (bench/train.py --compile)" \
  "$PY" bench/train.py --device cuda --steps 10 --full-steps 10 --compile
echo "results: $OUT"
