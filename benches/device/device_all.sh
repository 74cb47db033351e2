#!/usr/bin/env bash
# One lease, everything issue 4 still measures, most important first, each part cut off so the
# whole fits one call of the device tool (~560 s): the lego 800x800 5-minute run (test PSNR every
# minute, samples/s, rendering frames/s; examples/ablations/h100_lego.toml), the cooperative-matrix
# tests on hardware (mlp_coop, linear), the short per-path runs of both fields with pose refinement
# (examples/ablations/device_quick.toml) and a short kernel bench (the pose kernels' rows included).
# Brings back 8 files (the tool's limit). Build and pack here first: `bash benches/device/prepare.sh --rebuild`; carry .gl .bin .bint .data.
set -u
t0=$(date +%s); left() { echo $(( ${BUDGET:-560} - ($(date +%s) - t0) )); }
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig; export XDG_RUNTIME_DIR=/tmp
(cd .bin && xz -dc nerf.xz > nerf && chmod +x nerf) && tar xJf .bint/tests3.tar.xz -C .bin
{ nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv; cat .bin/COMMIT; } | tee "$OUT/gpu.txt"
echo "== lego ($(left) s left)"
timeout 380 .bin/nerf ablate examples/ablations/h100_lego.toml --device gpu --out /tmp/abl > "$OUT/lego.log" 2>&1
cat /tmp/abl/results.md >> "$OUT/lego.log" 2>/dev/null
for d in /tmp/abl/runs/*/; do cp "$d/metrics.json" "$OUT/lego_metrics.json"; cp "$d/curve.csv" "$OUT/lego_curve.csv"; done 2>/dev/null
tail -3 "$OUT/lego.log"; cat "$OUT/lego_curve.csv" 2>/dev/null
echo "== coop tests ($(left) s left)"
for t in mlp_coop linear; do
  echo "== $t"; timeout 45 ".bin/t3/$t" --test-threads=1 --nocapture --skip emulated 2>&1 | grep -vE "^\s+[0-9]+:|^\s+at " | tail -40
done > "$OUT/tests.log" 2>&1
grep -E "test result|panicked|NOTICE|GPU tests on|ooperative|FAILED|^test " "$OUT/tests.log" | head -40
echo "== quick ablation ($(left) s left)"
timeout $(( $(left) - 45 )) .bin/nerf ablate examples/ablations/device_quick.toml --device gpu --out /tmp/q > "$OUT/quick.log" 2>&1
cp /tmp/q/results.md "$OUT/quick_results.md" 2>/dev/null; cat "$OUT/quick_results.md" 2>/dev/null
echo "== kernel bench ($(left) s left)"
timeout $(( $(left) - 3 )) .bin/t3/kernels-bench --bench --warm-up-time 0.3 --measurement-time 0.7 > "$OUT/bench.log" 2>&1
grep -E "^[a-z_]+/|time:|thrpt:|gpu_kernels" "$OUT/bench.log" | head -80
echo "== done ($(left) s left)"
