#!/usr/bin/env bash
# On the lent H100: where a training step spends its GPU time, per field and MLP path
# (examples/ablations/h100_profile.toml: in-repo scene, 1200 steps each, steps 1000..1019 timed
# pass by pass; ~7 min). Expects .gl and .bin/nerf.xz (bash benches/device/prepare.sh makes them).
# Writes the ablation log (with the profile tables) and each run's record (gpu_profile inside).
set -u
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig; export XDG_RUNTIME_DIR=/tmp
(cd .bin && xz -dc nerf.xz > nerf && chmod +x nerf)
.bin/nerf ablate examples/ablations/h100_profile.toml --device gpu --out /tmp/prof > "$OUT/profile.log" 2>&1
cp /tmp/prof/results.md /tmp/prof/results.csv "$OUT/" 2>/dev/null
for d in /tmp/prof/runs/*/; do cp "$d/metrics.json" "$OUT/$(basename "$d").json" 2>/dev/null; done
grep -E "GPU profile|^\| [a-z]" "$OUT/profile.log" | head -150; cat "$OUT/results.md"
# The same hash run launched for the capacity (NERF_NO_INDIRECT) and from the device's count
# (~2 min): the A/B of indirect dispatch.
for mode in direct indirect; do
  env $([ $mode = direct ] && echo NERF_NO_INDIRECT=1) .bin/nerf ablate examples/ablations/h100_indirect.toml \
    --device gpu --out /tmp/ind_$mode > "$OUT/indirect_$mode.log" 2>&1
  cp /tmp/ind_$mode/results.md "$OUT/indirect_$mode.md" 2>/dev/null
  echo "== $mode"; cat "$OUT/indirect_$mode.md"
done
