#!/usr/bin/env bash
# Fit or generalisation? After a 5-minute lego run (device_session.sh or lego_variant.sh) on the
# same warm machine: score its kept checkpoint on lego's *training* views (every 4th: 25 views),
# rendered and scored exactly as the test views are (`nerf eval --split train`: white
# background, whole images). The gap to the test PSNR (eval_half.sh) says where the missing dB
# are: a field that scores far higher on the views it was trained on fits them and fails to
# generalise (a case for losses on the geometry); one that scores about the same there is
# limited in fit (capacity, optimisation). The CPU's gaps are in docs/results.md ("Training
# views against test views").
#   run(command="bash benches/device/eval_train.sh", carry=[".gl", ".bin", ".data"], timeout_s=120)
# Brings back eval_train.json (per-view PSNR and SSIM, alpha_split).
# Build here first: `bash benches/device/prepare.sh` (makes .data).
set -u
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig; export XDG_RUNTIME_DIR=/tmp
(cd .bin && xz -dc nerf.xz > nerf && chmod +x nerf)
run=$(ls -d runs/device/lego/runs/*/ 2>/dev/null | head -1)
[ -n "$run" ] && [ -f "$run/checkpoint.bin" ] || { echo "no checkpoint under runs/device/lego/runs/: run a lego run first, on this warm machine"; exit 1; }
echo "== $run on the training views of .data/lego"
.bin/nerf eval "$run" .data/lego --split train --views every:4 --device gpu --out /tmp/eval_train --quiet
cp /tmp/eval_train/eval.json "$OUT/eval_train.json"
