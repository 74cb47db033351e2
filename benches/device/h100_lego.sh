#!/usr/bin/env bash
# On the lent H100: the hash field on lego 800x800 for 5 minutes with test PSNR every minute
# (examples/ablations/h100_lego.toml), plus the full output of two kernel tests. Expects
# .bin/nerf.xz, .bin/tests2.tar.xz and the scene in .data/lego (train views + every 8th test
# view: cp ../shared/data/nerf_synthetic/lego/{transforms_*.json,train} and test/r_{0,8,..}.png).
set -u
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig; export XDG_RUNTIME_DIR=/tmp
(cd .bin && xz -dc nerf.xz > nerf && chmod +x nerf && tar xJf tests2.tar.xz)
for t in .bin/t2/*; do "$t" --test-threads=1 2>&1 | grep -vE "^\s+[0-9]+:|^\s+at " | tail -30; done > "$OUT/tests2.log" 2>&1
.bin/nerf ablate examples/ablations/h100_lego.toml --device gpu --out /tmp/abl > "$OUT/ablate.log" 2>&1
cp /tmp/abl/results.md /tmp/abl/results.csv /tmp/abl/psnr_vs_time.png "$OUT/" 2>/dev/null
for d in /tmp/abl/runs/*/; do cp "$d/metrics.json" "$OUT/run_metrics.json"; cp "$d/curve.csv" "$OUT/curve.csv"; done
tail -5 "$OUT/ablate.log"; cat "$OUT/results.md"
