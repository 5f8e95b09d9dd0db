#!/usr/bin/env bash
# Recipe study on a lent GPU (BENCHMARKS.md, *Surfaces: carving concavities*, section 16): several variants of the
# concave preset ("arms"), each over several seeds, all fitted at once on one GPU, each fit followed by eval-geometry.
# One GPU runs many small fits side by side (the SDF step is launch-bound at 512 rays), so a whole seed x arm table
# fits in one device call; every fit in it gets about the same number of steps, so the arms compare at equal steps.
#
# Two steps from the repository root (the GPU machine reaches neither ../shared nor the package index):
#   here:   bash scripts/bench_gpu.sh prepare .gpudata      (its seed-31 mug is the scene used here)
#   there:  bash scripts/bench_gpu_recipes.sh .gpudata OUT 'NAME[:fit options]' ...
# e.g.      bash scripts/bench_gpu_recipes.sh .gpudata $OUT control 'slowdecay:--lr-decay 0.3' \
#               'lateramp:--set eikonal_ramp=[5000,6500]'
# Environment: SEEDS ("0 1 2"), ITERS (14000: a 10-minute fit's steps on the 2-core CPU), BUDGET (380 s: a cap per fit
# that leaves the evaluations time; with nine fits on an H100 each made ~24 steps a second, so the cap ends them at
# ~9.5k steps), DEADLINE (560 s: what is still running then is stopped, so the call returns inside its 10 minutes),
# RES (256), DEV (cuda), PY (python3), WORK (/tmp/nerfmeta_recipes).
# OUT gets log.txt (each step's exit status and time, GPU use every 20 s), results.json (per run: steps, time, test
# PSNR, stop reason and eval-geometry's JSON) and runs.tgz (configs, summaries, metrics and logs; no checkpoints,
# except of runs whose evaluation did not finish, so they can be evaluated elsewhere).
set -u
data=${1:?usage: bench_gpu_recipes.sh DATA OUT ARM...}; out=${2:?usage: bench_gpu_recipes.sh DATA OUT ARM...}; shift 2
[ $# -gt 0 ] || { echo "bench_gpu_recipes.sh: name at least one arm, e.g. control" >&2; exit 2; }
work=${WORK:-/tmp/nerfmeta_recipes}; py=${PY:-python3}; dev=${DEV:-cuda}
iters=${ITERS:-14000}; budget=${BUDGET:-380}; res=${RES:-256}; deadline=${DEADLINE:-560}; seeds=${SEEDS:-0 1 2}
scene=$data/col31/mug/mug_000
mkdir -p "$out" "$work"
start=$(date +%s)
stamp() { echo "$(( $(date +%s) - start )) s: $*" >> "$out/log.txt"; }
{ date -u; nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader; nproc
  "$py" -c "import torch; print('torch', torch.__version__)"; git log --oneline -1; } > "$out/log.txt" 2>&1
if [ "$dev" != cpu ]; then
    "$py" -m pip install -q --no-deps --no-build-isolation -e . > "$work/pip.txt" 2>&1 || stamp "pip install failed"
fi

one() {  # one NAME SEED [fit options...]: fit, then eval-geometry
    local name=$1 seed=$2 run=$work/$1_s$2
    shift 2
    OMP_NUM_THREADS=1 "$py" -m nerfmeta fit "$scene" --out "$run" --init scratch --preset concave --device "$dev" \
        --iters "$iters" --time-budget "$budget" --eval-every 0 --checkpoint-every 0 --eval-views 8 --renders 1 \
        --seed "$seed" "$@" > "$run.fit.log" 2>&1
    stamp "$name seed $seed: fit rc=$?"
    if [ -e "$work/.deadline" ]; then return; fi  # past the deadline: no evaluation (the call must return)
    OMP_NUM_THREADS=2 "$py" -m nerfmeta eval-geometry "$run" --gt "$scene" --resolution "$res" \
        --json-out "$run.geometry.json" > "$run.eval.log" 2>&1
    stamp "$name seed $seed: eval-geometry rc=$?"
}

rm -f "$work/.deadline"
(while sleep 20; do stamp "gpu $(nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader 2>&1)"; done) &
sampler=$!
pids=()
for seed in $seeds; do
    for arm in "$@"; do
        name=${arm%%:*}; options=""
        [[ $arm == *:* ]] && options=${arm#*:}
        # shellcheck disable=SC2086  # the arm's options are split into words on purpose
        one "$name" "$seed" $options &
        pids+=($!)
    done
done
(sleep "$deadline"; touch "$work/.deadline"; stamp "deadline: stopping what is left"
 pkill -f "nerfmeta (fit $scene --out|eval-geometry) $work/") &  # ours only, not every fit on the machine
watchdog=$!
wait "${pids[@]}"
kill "$sampler" "$watchdog" 2> /dev/null

"$py" - "$work" "$out/results.json" <<'EOF'
import json, sys
from pathlib import Path
work, rows = Path(sys.argv[1]), {}
for run in sorted(p for p in work.iterdir() if p.is_dir()):
    row = {}
    if (run / "summary.json").exists():
        summary = json.loads((run / "summary.json").read_text())
        row.update({k: summary.get(k) for k in ("iters", "time_s", "test_psnr", "test_ssim", "stop_reason", "samples_per_ray")})
    geometry = run.with_name(run.name + ".geometry.json")
    row["geometry"] = json.loads(geometry.read_text()) if geometry.exists() else None
    rows[run.name] = row
Path(sys.argv[2]).write_text(json.dumps(rows, indent=1, default=str))
EOF
# checkpoints only of the runs whose evaluation did not finish (they can be evaluated elsewhere)
excludes=(--exclude=renders)
for run in "$work"/*/; do
    name=$(basename "$run")
    [ -e "$work/$name.geometry.json" ] && excludes+=("--exclude=./$name/*.safetensors")
done
tar czf "$out/runs.tgz" -C "$work" "${excludes[@]}" . 2>> "$out/log.txt"
stamp "collected"
