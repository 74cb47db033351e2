#!/usr/bin/env bash
# A short lease's recheck of the build (~200 s): both fields' steps on the in-repo scene
# (examples/ablations/device_shader_checks.toml with the default checks: the hash field at 2^18
# trained samples per step, the paper's field with its default GEMMs and tape; 600 steps or 15 s
# each, profiles of steps 200-209), then examples/ablations/h100_lego60.toml: a minute of lego
# 800x800 with the preset and with the table's subgroup sums, each profiled from step 6000.
#   run(command="bash benches/device/recheck.sh", carry=[".gl", ".bin", ".data"], timeout_s=300)
# Build and pack here first: `bash benches/device/prepare.sh --rebuild`.
# Brings back recheck.log and the lego runs' metrics (lego60_<run>.json, with their train_log).
set -u
t0=$(date +%s)
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig; export XDG_RUNTIME_DIR=/tmp
(cd .bin && xz -dc nerf.xz > nerf && chmod +x nerf)
log="$OUT/recheck.log"
{ nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv; cat .bin/COMMIT; } | tee "$log"
echo "== in-repo scene ($(( $(date +%s) - t0 )) s)" | tee -a "$log"
timeout 80 .bin/nerf ablate examples/ablations/device_shader_checks.toml --device gpu --out /tmp/rc >> "$log" 2>&1
cat /tmp/rc/results.md 2>/dev/null | tee -a "$log"
echo "== lego 60 s ($(( $(date +%s) - t0 )) s)" | tee -a "$log"
timeout 190 .bin/nerf ablate examples/ablations/h100_lego60.toml --device gpu --out /tmp/l60 >> "$log" 2>&1
cat /tmp/l60/results.md 2>/dev/null | tee -a "$log"
for d in /tmp/l60/runs/*/; do n=$(basename "$d"); cp "$d/metrics.json" "$OUT/lego60_${n%%__*}.json"; done 2>/dev/null
grep -E "busy per step|^\| (field|hash|density|march|sampling|compact|occupancy)" "$log" | head -60
echo "== done ($(( $(date +%s) - t0 )) s)" | tee -a "$log"
