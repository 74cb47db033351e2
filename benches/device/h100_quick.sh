#!/usr/bin/env bash
# On the lent H100 (see ../shared/docs/gpu-device.md): the GPU test binaries (incl. the
# cooperative-matrix paths lavapipe lacks) and training throughput of both fields on the in-repo
# scene. Expects .bin/nerf.xz and .bin/tests.tar.xz built here; writes to $OUT.
set -u
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig; export XDG_RUNTIME_DIR=/tmp
(cd .bin && xz -dc nerf.xz > nerf && chmod +x nerf && tar xJf tests.tar.xz)
nvidia-smi --query-gpu=name,driver_version,clocks.max.sm --format=csv > "$OUT/gpu.txt" 2>&1
for t in .bin/t/*; do
  echo "== $t"; "$t" --test-threads=1 --skip every_shader_validates --nocapture 2>&1 | grep -E "test result|panicked|NOTICE|ooperative|FAILED|GPU tests on"
done > "$OUT/tests.log" 2>&1
cat "$OUT/tests.log"
run() { local name=$1; shift; .bin/nerf train scenes/lego_100 --device gpu --quiet --no-renders --out "/tmp/$name" "$@" > "$OUT/$name.txt" 2>&1; cp "/tmp/$name/metrics.json" "$OUT/$name.json" 2>/dev/null; tail -2 "$OUT/$name.txt"; }
run hash18 --config configs/gpu_hash.toml --iters 3000 --time-budget 30 --test-views every:8
run freq --field freq --iters 400 --time-budget 30 --test-views first:2
