#!/usr/bin/env bash
# CUDA check and GPU figures for a lent GPU machine (BENCHMARKS.md, "On a GPU").
#
# Two steps from the repository root, because the GPU machine reaches neither ../shared nor the package index:
#   here:      bash scripts/bench_gpu.sh prepare .gpudata     (beer, lego at 100x100, a 128 px mug; ~8 MB;
#              list /.gpudata/ in .git/info/exclude and carry it to the GPU machine)
#   there:     bash scripts/bench_gpu.sh run .gpudata OUT [SECONDS]
# 'run' installs nerfmeta into the machine's Python (no dependencies: torch, torchvision, numpy, imageio,
# matplotlib, safetensors, tqdm, scipy and scikit-image are expected there; LPIPS is reported as
# unavailable without its weights), then
#   1. runs every command that takes --device on cuda on a tiny generated collection (fit for each
#      backbone, render, mesh, eval-geometry, classifier train and classify, pretrain, meta-train, an
#      --init auto fit with --compare scratch) and says which ones failed;
#   2. fits beer for 120 s on cuda, with our poses (beer_sfm, made by 'prepare') and with the shipped ones ($BEER
#      picks), times its test renders (scripts/bench_render.py) and renders a video along the capture's walk;
#   3. fits lego at 100x100 with the default route and with the scratch grid (SECONDS each, default 30);
#   4. fits the 128 px mug's surface (the README's concave-object recipe, 512 rays a step, for $MUG_SECONDS,
#      default 300 s: more steps than the CPU's 10 minutes give) and scores it.
# Every step's exit status and wall time go to OUT/log.txt; the runs' summaries to OUT/summaries.json.
# A table of recipe variants x seeds of the mug's surface, all at once on the GPU: scripts/bench_gpu_recipes.sh.
set -u

prepare() {
    local dest=$1 py=${PYTHON:-.venv/bin/python}
    mkdir -p "$dest"
    cp -r ../shared/data/real/beer "$dest/beer"
    # beer's own poses, from the full-size photos with the defaults: the shipped COLMAP poses fold its 540-degree
    # walk into four overlapping arcs (BENCHMARKS.md, "Poses from photos"); 'auto' matching keeps it whole
    "$py" -m nerfmeta poses ../shared/data/real/beer/images --out "$dest/beer_sfm" > /dev/null 2>&1 \
        || echo "nerfmeta poses failed on beer" >&2
    # lego at 100x100 as `--downscale 8` loads it: block means of premultiplied colour (compositing on
    # any background first and then averaging gives the same), alpha averaged, stored straight.
    "$py" - "$dest/lego100" <<'EOF'
import json, sys
from pathlib import Path
import imageio.v3 as iio
import numpy as np
src, dst = Path("../shared/data/nerf_synthetic/lego"), Path(sys.argv[1])
meta = json.loads((src / "transforms_train.json").read_text())
for frame in meta["frames"]:
    image = iio.imread(src / f"{frame['file_path']}.png").astype(np.float64) / 255
    h, w = image.shape[0] // 8, image.shape[1] // 8
    alpha = image[..., 3:].reshape(h, 8, w, 8, 1).mean((1, 3))
    prem = (image[..., :3] * image[..., 3:]).reshape(h, 8, w, 8, 3).mean((1, 3))
    rgb = np.where(alpha > 0, prem / np.maximum(alpha, 1e-12), 0)
    out = dst / f"{frame['file_path']}.png"
    out.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(out, (np.concatenate([rgb, alpha], -1).clip(0, 1) * 255).round().astype(np.uint8))
(dst / "transforms_train.json").write_text(json.dumps(meta))
EOF
    "$py" -m nerfmeta make-collection "$dest/col31" --categories mug --scenes-per-category 1 --views 40 \
        --test-views 8 --resolution 128 --seed 31 > /dev/null
    du -sh "$dest"
}

run() {
    local data=$1 out=$2 seconds=${3:-30} py=${PYTHON:-python3}
    local work=/tmp/nerfmeta_gpu log=$out/log.txt
    mkdir -p "$out" "$work"
    : > "$log"
    step() {  # step NAME TIMEOUT CMD...: run, log the exit status and wall time, go on either way
        local name=$1 limit=$2 start rc
        shift 2
        start=$(date +%s.%N)
        timeout "$limit" "$@" > "$work/$name.log" 2>&1
        rc=$?
        printf '%-22s rc=%-3s %6.1f s\n' "$name" "$rc" "$(awk -v a="$start" -v b="$(date +%s.%N)" 'BEGIN { print b - a }')" \
            | tee -a "$log"
        if [ "$rc" != 0 ]; then tr '\r' '\n' < "$work/$name.log" | grep -v "it/s\|s/it" | tail -12 >> "$log"; fi
    }
    local nm="$py -m nerfmeta"
    {
        date -u; nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
        "$py" -c "import torch; print('torch', torch.__version__)"; "$py" -m pip list 2>/dev/null | grep -i "^torchvision "
        nproc
    } >> "$log" 2>&1
    "$py" -m pip install -q --no-deps --no-build-isolation -e . >> "$log" 2>&1 || echo "pip install failed" >> "$log"
    local tiny=$work/tiny scene=$work/tiny/car/car_000 device=${DEVICE:-cuda} parts=${PARTS:-1234}
    local gpu="--device $device"
    local iters=${ITERS:-300}
    local fast="--iters $iters --eval-every 100 --checkpoint-every 100 --renders 1"

    # 1. every command that takes --device, on cuda (or on $DEVICE; PARTS=13 runs parts 1 and 3 only)
    if [[ $parts == *1* ]]; then
    step collection 120 $nm make-collection "$tiny" --categories car,mug --scenes-per-category 4 --views 12 \
        --test-views 3 --resolution 32 --seed 5 --val-fraction 0.25 --test-fraction 0.25
    # independent chains at the same time (the GPU and 16 cores have room; their wall times overlap)
    (for backbone in grid nerf dense; do
        step "fit_$backbone" 120 $nm fit "$scene" --out "$work/fit_$backbone" --backbone "$backbone" --init scratch $gpu $fast
    done
    step fit_resume 60 $nm fit "$scene" --out "$work/fit_grid" --resume --iters $((iters + 50)) $gpu
    step render_orbit 60 $nm render "$work/fit_grid" --out "$work/orbit.gif" --path orbit --frames 8 $gpu) &
    (step fit_sdf 120 $nm fit "$scene" --out "$work/fit_sdf" --backbone sdf --init scratch $gpu $fast
    step mesh 60 $nm mesh "$work/fit_sdf" --out "$work/sdf.ply" --resolution 64
    step eval_geometry 60 $nm eval-geometry "$work/fit_sdf" --gt "$scene" --resolution 64 --points 100000) &
    (step classifier_train 180 $nm classifier train "$tiny" --out "$work/classifier" --time-budget 30 --epochs 2 $gpu
    step classify 60 $nm classify "$scene" --classifier "$work/classifier" $gpu) &
    (step pretrain 120 $nm pretrain category "$tiny" --out "$work/prior_car" --category car --iters 450 --max-scenes 2 $gpu
    step fit_category 120 $nm fit "$scene" --out "$work/fit_cat" --init "category:$work/prior_car" $gpu $fast) &
    (step meta_train 180 $nm meta-train "$tiny" --out "$work/meta" --backbone nerf --meta-steps 5 --meta-batch 2 $gpu
    step fit_meta 120 $nm fit "$scene" --out "$work/fit_meta" --init "meta:$work/meta" $gpu $fast) &
    (step fit_auto_compare 180 $nm fit "$scene" --out "$work/fit_auto" --backbone nerf --compare scratch $gpu $fast) &
    wait
    fi

    # 2. beer, the real capture (#16's recipe), and its test renders
    if [[ $parts == *2* ]]; then
    # --iters 1000000: the budget ends the fit, not the default 3000 iterations (a GPU makes those in ~50 s here)
    # BEER: which of the two pose sets (the shipped ones, ours from the full-size photos; both at --downscale 4:
    # 180 x 320 and 178 x 316); each gets a fit, its timed test renders and a video along the capture's walk
    local name
    for name in ${BEER:-beer_sfm beer}; do
        step "${name}_fit" 240 $nm fit "$data/$name" --out "$work/$name" --downscale 4 --init scratch \
            --backbone grid --time-budget 120 --iters 1000000 --eval-every 500 $gpu
        step "${name}_render" 120 "$py" scripts/bench_render.py "$work/$name" --device "$device" --views 3
        step "${name}_video" 120 $nm render "$work/$name" --out "$out/${name}_walk.gif" --path walk --frames 24 $gpu
        cp "$work/${name}_render.log" "$out/${name}_render.txt" 2>/dev/null
        mkdir -p "$out/$name"
        cp "$work/$name"/{summary.json,metrics.jsonl,psnr_vs_time.png} "$work/$name"/renders/*.png "$out/$name/" 2>/dev/null
    done
    fi

    # 3. lego at 100x100: the default route against the scratch grid
    if [[ $parts == *3* ]]; then
    step lego_default $((seconds + 90)) $nm fit "$data/lego100" --out "$work/lego_default" --time-budget "$seconds" \
        --iters 1000000 $gpu
    step lego_scratch $((seconds + 90)) $nm fit "$data/lego100" --out "$work/lego_scratch" --init scratch --backbone grid \
        --time-budget "$seconds" --iters 1000000 $gpu
    fi

    # 4. the mug's surface with more compute than the CPU's 10 minutes give
    if [[ $parts == *4* ]]; then
    local mug_seconds=${MUG_SECONDS:-300}
    step mug_sdf $((mug_seconds + 120)) $nm fit "$data/col31/mug/mug_000" --out "$work/mug" --init scratch --preset concave \
        --time-budget "$mug_seconds" --iters 1000000 --eval-every 0 --checkpoint-every 0 --eval-views 8 --renders 2 $gpu
    step mug_geometry 180 $nm eval-geometry "$work/mug" --gt "$data/col31/mug/mug_000" --resolution 256 \
        --json-out "$out/mug_geometry.json"
    fi

    "$py" - "$work" "$out/summaries.json" <<'EOF'
import json, sys
from pathlib import Path
keep = ("route", "iterations", "final_psnr", "test_psnr", "test_ssim", "wall_seconds", "train_seconds", "seconds",
        "samples_per_ray", "geometry", "speedup", "compare")
found = {}
for summary in sorted(Path(sys.argv[1]).glob("**/summary.json")):
    data = json.loads(summary.read_text())
    found[str(summary.parent.relative_to(sys.argv[1]))] = {k: v for k, v in data.items() if k in keep} or data
Path(sys.argv[2]).write_text(json.dumps(found, indent=1, default=str))
EOF
    date -u >> "$log"
}

case "${1:-}" in
    prepare) prepare "${2:?usage: bench_gpu.sh prepare DEST}" ;;
    run) run "${2:?usage: bench_gpu.sh run DATA OUT [SECONDS]}" "${3:?usage: bench_gpu.sh run DATA OUT [SECONDS]}" "${4:-30}" ;;
    *) echo "usage: bench_gpu.sh prepare DEST | run DATA OUT [SECONDS]" >&2; exit 2 ;;
esac
