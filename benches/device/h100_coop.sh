#!/usr/bin/env bash
# On a lent GPU with cooperative matrices (the H100): the checks of the cooperative-matrix fused
# MLP (shaders/mlp_fused_coop.wgsl) and of rendering in rounds that lavapipe cannot make, then the
# plain-vs-coop ablation (examples/ablations/h100_coop.toml). Build here first:
#   cargo build --release -p nerf-cli && strip -o .bin/nerf target/release/nerf && xz -f .bin/nerf
#   cargo test --release -p nerf-gpu --test mlp_coop --test sampling --no-run
#   cargo test --release -p nerf-field-hash --test gpu --no-run
#   cargo bench -p nerf-gpu --bench kernels --no-run
#   mkdir -p .bin/t3 && cp <the printed test/bench executables> .bin/t3/ && tar cJf .bin/tests3.tar.xz -C .bin t3
# and copy the scene into .data/lego (benches/device/h100_lego.sh says how); carry .gl, .bin, .data.
set -u
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig; export XDG_RUNTIME_DIR=/tmp
(cd .bin && xz -dc nerf.xz > nerf && chmod +x nerf && tar xJf tests3.tar.xz)
for t in .bin/t3/mlp_coop-* .bin/t3/sampling-* .bin/t3/gpu-*; do
  echo "== $t"; "$t" --test-threads=1 --nocapture 2>&1 | grep -vE "^\s+[0-9]+:|^\s+at " | tail -40
done > "$OUT/tests3.log" 2>&1
grep -E "test result|panicked|NOTICE|GPU tests on" "$OUT/tests3.log"
for b in .bin/t3/kernels-*; do "$b" --bench fused_mlp > "$OUT/bench_fused_mlp.log" 2>&1; done
grep -E "^fused|time:|thrpt:" "$OUT/bench_fused_mlp.log" | head -40
.bin/nerf ablate examples/ablations/h100_coop.toml --device gpu --out /tmp/abl > "$OUT/ablate.log" 2>&1
cp /tmp/abl/results.md /tmp/abl/results.csv "$OUT/" 2>/dev/null
tail -5 "$OUT/ablate.log"; cat "$OUT/results.md"
