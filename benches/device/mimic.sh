#!/usr/bin/env bash
# The CPU's 16x scaled-down lego run (examples/ablations/h100_mimic_lego200.toml: 200x200, 2^14
# samples per step, finest level 512, 2^15 table entries, the H100 run's 43 k steps) trained on the
# GPU. Its CPU results are known (docs/results.md, "The H100's run scaled down 16x"): the GPU
# matching them in this long regime says the GPU trainer is the CPU's at 43 k steps, as the
# parity runs showed for 6000; the table's row (`t16`) then says whether a larger table gains at
# this scale on the GPU too, where the 5-minute run at 800x800 showed none. RUNS picks runs by
# name (default: t15 and t16; `t15_distortion_001` is the third). ~1-2 minutes per run.
#   run(command="bash benches/device/mimic.sh", carry=[".gl", ".bin", ".data"], timeout_s=400)
# Brings back mimic_results.csv and each run's metrics (mimic_<run>.json, with train_log).
set -u
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig; export XDG_RUNTIME_DIR=/tmp
(cd .bin && xz -dc nerf.xz > nerf && chmod +x nerf)
runs=${RUNS:-t15 t16}
# The scene path of the device's copy of lego (benches/device/prepare.sh), and only the runs asked for.
src=examples/ablations/h100_mimic_lego200.toml
dst=examples/ablations/mimic_device.toml
sed 's|\.\./\.\./\.\./shared/data/nerf_synthetic/lego|../../.data/lego|' "$src" | awk -v keep="$runs" '
  BEGIN { n = split(keep, k, " "); for (i = 1; i <= n; i++) want["name = \"" k[i] "\""] = 1 }
  /^\[\[runs\]\]/ { inrun = 1; held = $0; next }
  inrun && /^name = / { on = ($0 in want); if (on) { print held; print }; next }
  inrun { if (on) print; next }
  { print }' > "$dst"
grep -c '^\[\[runs\]\]' "$dst" | sed "s/$/ runs: $runs/"
timeout 560 .bin/nerf ablate "$dst" --device gpu --out runs/device/mimic > "$OUT/mimic.log" 2>&1
cp runs/device/mimic/results.csv "$OUT/mimic_results.csv" 2>/dev/null
for d in runs/device/mimic/runs/*/; do n=$(basename "$d"); cp "$d/metrics.json" "$OUT/mimic_$n.json"; done 2>/dev/null
grep "test PSNR" "$OUT/mimic.log"; tail -2 "$OUT/mimic.log"
