#!/usr/bin/env bash
# The cost of `predict --sun-tune 30` against the default, whole processes, A/B in turn (bench/results/predict.md,
# "--sun-tune's cost"). Usage: bash bench/sun_tune_pair.sh CHECKPOINT ORTHO [WORKDIR]
#   CHECKPOINT: a small-area run's best.pt with a sun fit (experiments/heights_from_the_sun's runs/s0/best.pt)
#   ORTHO: a 2048 x 2048 px orthophoto at the model's GSD (autzen_west's orthophoto at 1 m, one tile of it)
set -u
M=${1:?checkpoint}; I=${2:?orthophoto}; W=${3:-$(mktemp -d)}
cd "$W"
echo "# $(date -u) load $(cut -d' ' -f1-3 /proc/loadavg) HEAD $(git -C /work/main rev-parse --short HEAD)"
farm-bench -n 3 --warmup 1 --timeout 900 --vs "sh -c 'exec aerialmtl predict $I --model $M --mc 8 --out B --overwrite --quiet'" -- sh -c "exec aerialmtl predict $I --model $M --mc 8 --out A --overwrite --quiet --sun-tune 30" 2>&1 | grep -E "wall|cpu s|A/B|exit|peak"
echo "# done load $(cut -d' ' -f1-3 /proc/loadavg)"
python - <<'PY'
import json
for d in ("A", "B"):
    p = json.load(open(f"{d}/prediction.json")); print(d, {k: round(v, 2) for k, v in p["timings_s"].items()}, p.get("sun_tune"))
PY
