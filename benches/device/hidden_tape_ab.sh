#!/usr/bin/env bash
# The paper's field with and without the f32 tape of its hidden layers (`gpu_hidden_tape`; since
# 2026-11-27 dropped by default on cooperative matrices) on the device (~100 s): first the hardware test (`linear`'s coop_mlp_trains_the_same_without_its_hidden_tape
# and the tiled path against the CPU twin), then examples/ablations/device_hidden_tape.toml (both
# runs 600 steps or 15 s, with a profile window) and the kernel bench's trunk rows with and
# without the tape. A call of its own on the warm machine:
#   run(command="bash benches/device/hidden_tape_ab.sh", carry=[".gl", ".bin", ".bint"], timeout_s=200)
# Build and pack here first: `DEVICE_TESTS="linear kernels-bench" bash benches/device/prepare.sh --rebuild`.
# Brings back hidden_tape_ab.log.
set -u
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig; export XDG_RUNTIME_DIR=/tmp
(cd .bin && xz -dc nerf.xz > nerf && chmod +x nerf) && tar xJf .bint/tests3.tar.xz -C .bin
log="$OUT/hidden_tape_ab.log"
cat .bin/COMMIT | tee -a "$log"
echo "== linear (hardware)" | tee -a "$log"
timeout 60 .bin/t3/linear --test-threads=1 hidden_tape coop_tiled_mlp_matches 2>&1 | grep -vE "^\s+[0-9]+:|^\s+at " | tail -15 | tee -a "$log"
echo "== ablation" | tee -a "$log"
timeout 60 .bin/nerf ablate examples/ablations/device_hidden_tape.toml --device gpu --out /tmp/tape >> "$log" 2>&1
cat /tmp/tape/results.md 2>/dev/null | tee -a "$log"
echo "== kernel bench" | tee -a "$log"
timeout 60 .bin/t3/kernels-bench --bench --warm-up-time 0.2 --measurement-time 0.5 "trunk_8x256_coop" 2>&1 | grep -E "time:" -B1 | grep -vE "^--" | tee -a "$log"
