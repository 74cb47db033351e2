#!/usr/bin/env bash
# A short device check (~3 min) of a session's GPU changes: the tiled cooperative-matrix GEMM tests
# on hardware (linear), the hash and paper fields on the in-repo scene
# (examples/ablations/device_check.toml, the before/after of device_quick.toml's runs), a pass-by-
# pass profile of the paper field on the plain-WGSL GEMMs (a few steps) and the fused-MLP, hash-grid and
# trunk rows of the kernel bench. Build and pack here first: `bash benches/device/prepare.sh
# --rebuild`; carry .gl .bin .bint (the bench and `linear` alone are enough in .bint).
set -u
t0=$(date +%s); left() { echo $(( ${BUDGET:-250} - ($(date +%s) - t0) )); }
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig; export XDG_RUNTIME_DIR=/tmp
(cd .bin && xz -dc nerf.xz > nerf && chmod +x nerf) && tar xJf .bint/tests3.tar.xz -C .bin
{ nvidia-smi --query-gpu=name,driver_version --format=csv,noheader; cat .bin/COMMIT; } | tee "$OUT/gpu.txt"
echo "== linear ($(left) s left)"
timeout 40 .bin/t3/linear --test-threads=1 --skip emulated 2>&1 | grep -vE "^\s+[0-9]+:|^\s+at " > "$OUT/tests.log"
grep -E "test result|panicked|NOTICE|Caused|Binding|FAILED" "$OUT/tests.log" | head -20
echo "== fields ($(left) s left)"
timeout 90 .bin/nerf ablate examples/ablations/device_check.toml --device gpu --out /tmp/q > "$OUT/check.log" 2>&1
cat /tmp/q/results.md 2>/dev/null
echo "== bench ($(left) s left)"
timeout 60 .bin/t3/kernels-bench --bench --warm-up-time 0.2 --measurement-time 0.5 "fused_mlp_(density|color)|trunk|hash_grid_(forward|backward|input)" > "$OUT/bench.log" 2>&1
grep -E "time:" -B1 "$OUT/bench.log" | grep -vE "^--" | head -40
echo "== freq plain ($(left) s left)"
printf 'field = "freq"\ngpu_profile = { start = 2, steps = 2 }\n[field_config]\ngpu_linear = "plain"\n' > /tmp/fp.toml
timeout $(( $(left) - 3 )) .bin/nerf train scenes/lego_100 --config /tmp/fp.toml --iters 5 --device gpu --quiet --no-renders \
  --test-views first:1 --out /tmp/fp > "$OUT/freq_plain.log" 2>&1
cp /tmp/fp/gpu_profile.json "$OUT/freq_plain_profile.json" 2>/dev/null
grep -E "GPU profile|^\| [a-z]" "$OUT/freq_plain.log" | head -32; tail -2 "$OUT/freq_plain.log"
echo "== done ($(left) s left)"
