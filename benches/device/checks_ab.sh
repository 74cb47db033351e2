#!/usr/bin/env bash
# wgpu's shader runtime checks on the device (~100 s): examples/ablations/device_shader_checks.toml
# (the hash field at 2^18 samples per step, the paper's field with its default GEMMs; 600 steps or
# 15 s each) with wgpu's shader runtime checks (NERF_GPU_CHECKS=on: index clamps on fixed-size
# arrays, loop counters) and without (=off, the default on hardware since 2026-11-27; D's numbers
# are in docs/results.md), then the kernel bench's trunk, hash-grid and
# fused-MLP rows both ways. Its own call on the warm machine (~2 min), after device_session.sh:
#   run(command="bash benches/device/checks_ab.sh", carry=[".gl", ".bin", ".bint"], timeout_s=200)
# Brings back checks_ab.log.
set -u
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig; export XDG_RUNTIME_DIR=/tmp
(cd .bin && xz -dc nerf.xz > nerf && chmod +x nerf)
[ -f .bint/tests3.tar.xz ] && tar xJf .bint/tests3.tar.xz -C .bin
log="$OUT/checks_ab.log"
for mode in on off; do
  export NERF_GPU_CHECKS=$mode
  echo "== shader checks $mode" | tee -a "$log"
  timeout 60 .bin/nerf ablate examples/ablations/device_shader_checks.toml --device gpu --out /tmp/checks_$mode >> "$log" 2>&1
  cat /tmp/checks_$mode/results.md 2>/dev/null | tee -a "$log"
  [ -x .bin/t3/kernels-bench ] && timeout 40 .bin/t3/kernels-bench --bench --warm-up-time 0.2 --measurement-time 0.5 \
    "trunk|hash_grid_(forward|backward)/|fused_mlp_(density|color)_[0-9_]+_forward_backward" 2>&1 | grep -E "time:" -B1 | grep -vE "^--" | tee -a "$log"
done
unset NERF_GPU_CHECKS
