#!/usr/bin/env bash
# Run HERE (not on the device): score a field that lego_variant.sh brought home in parts
# (slim.ckpt.0, .1, ...: its render-only copy, `nerf slim`) on all 200 of lego's test views, on
# white (the target's protocol), with this machine's build, on the CPU unless a GPU is here.
#   bash benches/device/score_here.sh FILES_AT NAME [STEP]
# FILES_AT: the folder the device tool put the call's files in (its `files_at`); NAME: a folder
# name under runs/home/ (git-ignored). With STEP (e.g. 0.0025) the field is scored again with that
# marching step (`nerf eval --step-size`). Writes runs/home/NAME/eval_all[_step]/eval.json and
# prints the mean PSNR and SSIM; 800×800 views take a while on 2 cores (see docs/gpu.md).
# The training views (every 4th, `--split train`) are scored with TRAIN=1; VIEWS=first:4 (any
# `--test-views` value) scores fewer test views, for a quick look. SPP=8 (with STEP) scores the
# views once more at that step with 8 rays per pixel (`nerf eval --spp`, eval_all_step_spp8/):
# ~1.7 hours for the 200 views on 2 cores. FILTER=F with SPP scores those rays once more placed
# by the pixel filter F (`nerf eval --filter`, e.g. blackman-harris), eval_all_step_sppN_filter/.
set -euo pipefail
cd "$(dirname "$0")/../.."
src=${1:?usage: score_here.sh FILES_AT NAME [STEP]}
name=${2:?usage: score_here.sh FILES_AT NAME [STEP]}
step=${3:-}
scene=${SCENE:-../shared/data/nerf_synthetic/lego}
ls "$src"/slim.ckpt.* >/dev/null 2>&1 || { echo "$src holds no slim.ckpt.* parts (lego_variant.sh brings them back)"; exit 1; }
[ -d "$scene" ] || { echo "no scene at $scene (set SCENE)"; exit 1; }
run=runs/home/$name
mkdir -p "$run"
# The parts in order (split -d -a 1 numbers them 0..9, so the glob's order is theirs). A missing
# part shows as a truncated checkpoint when it is read.
cat "$src"/slim.ckpt.? > "$run/checkpoint.bin"
export XDG_RUNTIME_DIR=${XDG_RUNTIME_DIR:-/tmp}
[ -x target/release/nerf ] || cargo build --release -p nerf-cli
nerf=target/release/nerf
score() {
  local out=$1; shift
  "$nerf" eval "$run" "$scene" --device "${DEVICE:-auto}" --quiet --out "$run/$out" "$@"
  python3 -c "import json,sys; e=json.load(open(sys.argv[1])); print(f\"$out: {e['test_psnr']:.3f} dB, SSIM {e['test_ssim']:.4f} over {e['n_test_views']} views\")" "$run/$out/eval.json"
}
score eval_all --test-views "${VIEWS:-all}"
[ -n "$step" ] && score eval_all_step --test-views "${VIEWS:-all}" --step-size "$step"
[ -n "$step" ] && [ -n "${SPP:-}" ] && score "eval_all_step_spp$SPP" --test-views "${VIEWS:-all}" --step-size "$step" --spp "$SPP"
[ -n "$step" ] && [ -n "${SPP:-}" ] && [ -n "${FILTER:-}" ] && score "eval_all_step_spp${SPP}_filter" --test-views "${VIEWS:-all}" --step-size "$step" --spp "$SPP" --filter "$FILTER"
[ "${TRAIN:-0}" = 1 ] && score eval_train --split train --views every:4
exit 0
