#!/usr/bin/env bash
# The second and third calls of a lease, right after device_session.sh on the same warm machine:
# score the lego run's kept checkpoint (h100_lego.toml has `checkpoints = true`; the run's folder
# is runs/device/lego/runs/*/, ignored by git and so kept between calls) on half of lego's 200
# test views. One call cannot carry all 200 beside the training views (64 MiB), hence halves:
#   run(command="bash benches/device/eval_half.sh a", carry=[".gl", ".bin", ".eval_a"])
#   run(command="bash benches/device/eval_half.sh b", carry=[".gl", ".bin", ".eval_b"])
# Each brings back eval_<half>.json (per-view PSNR and SSIM, alpha_split). Both halves hold 100
# views, so the mean over all 200 is the mean of the two halves' means. A second argument `both`
# also scores the half on black (instant-ngp's protocol; `nerf eval --background black`) into
# eval_<half>_black.json, ~5 s more: only meaningful for a run trained on random backgrounds.
# With STEP=S in the environment it also renders the half with the marching step S (`nerf eval
# --step-size S`, e.g. 0.0025, half the trained step) into eval_<half>_step.json, ~10 s more.
# With SPP=N it also renders each view as the mean of N rays through each pixel (`nerf eval --spp
# N`, e.g. 8: a lattice over the pixel; instant-ngp also scores with 8 per pixel, but at the
# centre with 8 marching offsets; with STEP, at that step as well) into eval_<half>_spp.json,
# ~2N times the plain render's time with STEP at half the trained step (estimated ~1 min per half
# for lego at 800x800 on an H200, from its 28 frames/s at 1 ray; not yet measured).
# With FILTER=F as well (e.g. blackman-harris: Blender Cycles' film filter, 1.5 px), those N rays
# are scored once more placed by that pixel filter (`nerf eval --filter F`) into
# eval_<half>_spp_filter.json, the same time again.
# Build here first: `bash benches/device/prepare.sh` (makes .eval_a and .eval_b).
set -u
half=${1:?usage: eval_half.sh a|b [both]}
both=${2:-}
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig; export XDG_RUNTIME_DIR=/tmp
(cd .bin && xz -dc nerf.xz > nerf && chmod +x nerf)
run=$(ls -d runs/device/lego/runs/*/ 2>/dev/null | head -1)
[ -n "$run" ] && [ -f "$run/checkpoint.bin" ] || { echo "no checkpoint under runs/device/lego/runs/: run device_session.sh first, on this warm machine"; exit 1; }
echo "== $run on .eval_$half/lego"
# score NAME [ARGS...]: the half rendered with `nerf eval ARGS` into $OUT/NAME.json, its scores printed.
score() {
  local name=$1; shift
  .bin/nerf eval "$run" ".eval_$half/lego" --test-views all --device gpu "$@" --out "/tmp/$name" --quiet || return
  cp "/tmp/$name/eval.json" "$OUT/$name.json"
  python3 -c "import json,sys; e=json.load(open(sys.argv[1])); print(f\"$name: {e['test_psnr']:.3f} dB, SSIM {e['test_ssim']:.4f}, {e['n_test_views']} views, spp {e.get('spp', 1)}, filter {e.get('filter', {}).get('kind', 'box')}, step {e.get('render_step_size')}\")" "$OUT/$name.json" 2>/dev/null || true
}
score "eval_$half"
[ "$both" = both ] && score "eval_${half}_black" --background black
[ -n "${STEP:-}" ] && score "eval_${half}_step" --step-size "$STEP"
if [ -n "${SPP:-}" ]; then
  extra=(--spp "$SPP"); [ -n "${STEP:-}" ] && extra+=(--step-size "$STEP")
  score "eval_${half}_spp" "${extra[@]}"
  [ -n "${FILTER:-}" ] && score "eval_${half}_spp_filter" "${extra[@]}" --filter "$FILTER"
fi
exit 0
