#!/usr/bin/env bash
# On a lent GPU with cooperative matrices (the H100): the checks of the cooperative-matrix fused
# MLP (shaders/mlp_fused_coop.wgsl), of the emulated cooperative-matrix kernels' hardware twin and of
# rendering in rounds that lavapipe cannot make, the hash backward's subgroup sums with 32-wide
# subgroups (encoding) and the fused MLP's activation rows (mlp), then the plain-vs-coop ablation
# (examples/ablations/h100_coop.toml). Build and pack here first: `bash benches/device/prepare.sh`
# (the binaries of a commit; .bin/COMMIT says which; its default .bint holds mlp_coop, linear and
# the bench, which fit beside .data: DEVICE_TESTS=all packs every GPU test executable, too many
# to carry with .data); carry .gl, .bin, .bint, .data (~60 MB with the working tree).
set -u
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig; export XDG_RUNTIME_DIR=/tmp
(cd .bin && xz -dc nerf.xz > nerf && chmod +x nerf) && tar xJf .bint/tests3.tar.xz -C .bin
for t in .bin/t3/*; do
  [ "$(basename "$t")" = kernels-bench ] && continue
  echo "== $t"; "$t" --test-threads=1 --nocapture 2>&1 | grep -vE "^\s+[0-9]+:|^\s+at " | tail -40
done > "$OUT/tests3.log" 2>&1
grep -E "test result|panicked|NOTICE|GPU tests on" "$OUT/tests3.log"
"$PWD/.bin/t3/kernels-bench" --bench > "$OUT/bench_kernels.log" 2>&1
grep -E "^[a-z_]+/|time:|thrpt:" "$OUT/bench_kernels.log" | head -60
.bin/nerf ablate examples/ablations/h100_coop.toml --device gpu --out /tmp/abl > "$OUT/ablate.log" 2>&1
cp /tmp/abl/results.md /tmp/abl/results.csv "$OUT/" 2>/dev/null
tail -5 "$OUT/ablate.log"; cat "$OUT/results.md"
