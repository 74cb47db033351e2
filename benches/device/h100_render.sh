#!/usr/bin/env bash
# On the lent H100: a short hash-field run on lego 800x800 (20 s) and its evaluation on 25 test
# views, for the rendering frames/s at 800x800 and a check of the final build on the device.
# Expects .gl, .bin/nerf.xz and .data/lego (bash benches/device/prepare.sh makes them).
set -u
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig; export XDG_RUNTIME_DIR=/tmp
(cd .bin && xz -dc nerf.xz > nerf && chmod +x nerf)
.bin/nerf train .data/lego --device gpu --config configs/gpu_hash.toml --time-budget 20 --test-views every:8 \
    --no-renders --quiet --out /tmp/r > "$OUT/render.txt" 2>&1
cp /tmp/r/metrics.json "$OUT/render_metrics.json"; tail -2 "$OUT/render.txt"
python3 -c "import json;m=json.load(open('$OUT/render_metrics.json'));print({k:m[k] for k in ['iterations','ms_per_iter','samples_per_sec','test_psnr','render_fps','eval_seconds']})" 2>/dev/null
