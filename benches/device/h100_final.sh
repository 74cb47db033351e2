#!/usr/bin/env bash
# On the lent H100: the lego 800x800 ablation (examples/ablations/h100_lego.toml, 5 minutes, PSNR
# every minute, rendering frames/s at 800x800). Expects .gl, .bin/nerf.xz and .data/lego (bash benches/device/prepare.sh makes them).
set -u
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig; export XDG_RUNTIME_DIR=/tmp
(cd .bin && xz -dc nerf.xz > nerf && chmod +x nerf)
.bin/nerf ablate examples/ablations/h100_lego.toml --device gpu --out /tmp/abl > "$OUT/ablate.log" 2>&1
cp /tmp/abl/results.md /tmp/abl/results.csv "$OUT/" 2>/dev/null
for d in /tmp/abl/runs/*/; do cp "$d/metrics.json" "$OUT/run_metrics.json"; cp "$d/curve.csv" "$OUT/curve.csv"; done
tail -3 "$OUT/ablate.log"; cat "$OUT/curve.csv"
