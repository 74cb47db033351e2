#!/usr/bin/env bash
# A lego training run on the device from an ablation file whose scene path is ../../.data/lego
# (examples/ablations/h100_lego*.toml, or on an H200 the step-matched h100eq_lego*.toml), into
# runs/device/lego (git-ignored, kept between calls on a warm machine; replaced by each call):
#   run(command="bash benches/device/lego_variant.sh FILE", carry=[".gl", ".bin", ".data"], timeout_s=400)
# Brings back variant_metrics.json (with train_log), variant_curve.csv and the trained field's
# render-only copy in parts (slim.ckpt.*; SLIM=0 skips it). Score the field on all 200 test views
# afterwards, on the same warm machine with eval_half.sh a and b (SPP=8 STEP=0.0025 as well), or
# here with score_here.sh FILES_AT NAME 0.0025 (SPP=8 too: ~1.7 h on 2 cores). What to run next
# and why: docs/gpu.md, "The next lease"; what each lease ran: docs/results.md.
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
