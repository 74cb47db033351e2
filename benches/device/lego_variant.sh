#!/usr/bin/env bash
# A second 5-minute lego run on the warm machine, after device_session.sh and the two
# eval_half.sh calls: FILE (a lego ablation whose scene path is ../../.data/lego, e.g.
# examples/ablations/h100_lego_occ_threshold.toml, a stricter occupancy grid, or
# h100_lego_tcnn_grid.toml, nerfacc's grid) against the preset run of device_session.sh, every
# 8th test view. Neither of those two beat the preset on the CPU (docs/results.md, 2026-11-27).
# It replaces runs/device/lego, so score device_session.sh's run there first if it is wanted.
#   run(command="bash benches/device/lego_variant.sh FILE", carry=[".gl", ".bin", ".data"], timeout_s=400)
# Brings back variant_metrics.json (with train_log), variant_curve.csv and the trained field's
# render-only copy in parts (slim.ckpt.*; SLIM=0 skips it): score it here with score_here.sh.
# Lease F (2026-11-27) ran h100_lego_table20.toml (no gain over the preset) and h100_lego.toml itself (the preset, for its
# checkpoint); next: h100_lego_batch19_res1024.toml (2^19 samples per step and the finest grid
# level at 1024 cells, +0.46 dB together in the CPU's scaled-down run, two seeds), then each alone,
# h100_lego_res1024.toml and h100_lego_batch19.toml (docs/gpu.md, "The next lease").
# On an H200 (the kind lent since 2026-11-28) run their step-matched twins instead, stopped at
# the steps the H100 makes in 5 minutes: lease G (2026-12-04) ran h100eq_lego_batch19_res1024.toml
# (35.38 dB on every 8th view) but lost its checkpoint; next: that file again, then
# h100eq_lego_batch19_res1024_sparse.toml, then h100eq_lego.toml, each scored here afterwards
# with score_here.sh (docs/gpu.md, "The next lease"). Since 2026-12-04 the sparse run is followed
# on the same warm machine by `SPP=8 STEP=0.0025 bash benches/device/eval_half.sh a` and `b`
# (all 200 test views with 8 rays per pixel at half the step, too slow to score here).
set -u
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig; export XDG_RUNTIME_DIR=/tmp
(cd .bin && xz -dc nerf.xz > nerf && chmod +x nerf)
file=${1:?usage: lego_variant.sh FILE (a lego ablation, e.g. examples/ablations/h100_lego_tcnn_grid.toml)}
# Into runs/device/lego (git-ignored, kept between calls), as device_session.sh's preset run: two
# calls of eval_half.sh on the same warm machine then score it on all 200 test views.
rm -rf runs/device/lego
timeout 380 .bin/nerf ablate "$file" --device gpu --out runs/device/lego > "$OUT/variant.log" 2>&1
for d in runs/device/lego/runs/*/; do cp "$d/metrics.json" "$OUT/variant_metrics.json"; cp "$d/curve.csv" "$OUT/variant_curve.csv"; done 2>/dev/null
# The trained field comes home too: its render-only copy (`nerf slim`: the averaged weights and the
# occupancy grid, ~55 MiB for lego at 2^19 entries per level) in 15-MiB parts, slim.ckpt.0, .1,
# ... (the tool brings back files of at most 16 MiB). Here, benches/device/score_here.sh joins
# them and scores the field on all 200 test views at any marching step, on the CPU, so the lease
# needs no eval_half.sh calls and nothing is lost when the machine goes back.
if [ "${SLIM:-1}" = 1 ] && [ -f "${d:-}/checkpoint.bin" ]; then
  rm -rf /tmp/slim && .bin/nerf slim "$d" --out /tmp/slim && split -b 15M -d -a 1 /tmp/slim/checkpoint.bin "$OUT/slim.ckpt."
  ls -l "$OUT"/slim.ckpt.* | awk '{print "  " $NF ": " $5 " bytes"}'
fi
tail -3 "$OUT/variant.log"; cat "$OUT/variant_curve.csv" 2>/dev/null
