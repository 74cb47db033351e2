#!/usr/bin/env bash
# Run HERE (not on the device), in the repository root, before the h100_*.sh scripts: builds and
# packs everything they expect into the git-ignored folders the device tool carries.
#   .gl/    the Vulkan loader and GLVND packages the device image lacks (../shared/docs/gpu-device.md)
#   .bin/   nerf.xz: the stripped release binary; COMMIT: the commit it was built from
#   .bint/  tests3.tar.xz: the stripped GPU test executables named in $DEVICE_TESTS (default
#           "mlp_coop linear kernels-bench": what device_all.sh and device_check.sh run; the
#           tool's 64 MiB do not hold all thirteen beside .data; dense_grid and voxel_gpu
#           check the voxel field's twin, run `voxel_gpu --skip training` there: its training
#           test reads the in-repo scene; plenoxels_gpu the out-of-tree field's, run
#           `plenoxels_gpu --skip training` there: its training test runs its binary) and the
#           kernel bench
#           (DEVICE_TESTS=all packs every one, for h100_coop.sh without .data)
#   .data/  lego: ../shared's lego scene, all train views and every 8th test view (h100_lego.sh,
#           h100_final.sh, h100_render.sh, h100_coop.sh)
#   .eval_a/, .eval_b/  lego: test views 0-99 and 100-199 with their own transforms_test.json
#           (eval_half.sh: all 200 test views in two calls)
# Then run e.g.:  run(command="bash benches/device/h100_profile.sh", carry=[".gl", ".bin"])
# (carry what the script's header names; the total must stay under the tool's 64 MiB).
# Each part is skipped when already there; `--rebuild` redoes .bin and .bint.
set -euo pipefail
cd "$(dirname "$0")/../.."
rebuild=0; [ "${1:-}" = "--rebuild" ] && rebuild=1

if ! ls .gl/*.deb >/dev/null 2>&1; then
  echo "== .gl: downloading the Vulkan loader and GLVND packages"
  mkdir -p .gl /tmp/amd64/partial
  o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
  apt-get $o update -qq
  (cd .gl && apt-get $o download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
fi

if [ $rebuild = 1 ] || [ ! -f .bin/nerf.xz ]; then
  echo "== .bin: release binary"
  mkdir -p .bin
  cargo build --release -p nerf-cli
  strip -o /tmp/nerf-stripped target/release/nerf
  xz -T0 -c /tmp/nerf-stripped > .bin/nerf.xz
  git rev-parse HEAD > .bin/COMMIT
  git diff --quiet HEAD || echo "(the working tree has uncommitted changes)" >> .bin/COMMIT
fi

if [ $rebuild = 1 ] || [ ! -f .bint/tests3.tar.xz ]; then
  echo "== .bint: GPU test executables and the kernel bench"
  rm -rf /tmp/t3 && mkdir -p /tmp/t3/t3 .bint
  # The executables cargo built, from its JSON messages: "<name>\t<path>".
  executables() {
    cargo "$@" --message-format=json 2>/dev/null | python3 -c '
import json, sys
for line in sys.stdin:
    try: m = json.loads(line)
    except ValueError: continue
    if m.get("reason") == "compiler-artifact" and m.get("executable"):
        print(m["target"]["name"] + "\t" + m["package_id"].split("#")[0].rstrip("/").split("/")[-1] + "\t" + m["executable"])'
  }
  {
    executables test --release -p nerf-gpu --test mlp_coop --test sampling --test linear --test optim --test profile --test compact --test encoding --test mlp --test dense_grid --no-run
    executables test --release -p nerf-field-hash --test gpu --no-run
    executables test --release -p nerf-field-freq --test gpu --no-run
    executables test --release -p nerf-field-voxel --test gpu --no-run
    executables test --release -p nerf-plenoxels --test gpu --no-run
    executables bench -p nerf-gpu --bench kernels --no-run
  } | while IFS=$'\t' read -r name pkg exe; do
    case "$pkg:$name" in
      *kernels) out=kernels-bench ;;
      *freq*:gpu) out=freq_gpu ;;
      *hash*:gpu) out=hash_gpu ;;
      *voxel*:gpu) out=voxel_gpu ;;
      *custom-field*:gpu) out=plenoxels_gpu ;;
      *) out=$name ;;
    esac
    case " ${DEVICE_TESTS:-mlp_coop linear kernels-bench} " in
      *" all "*|*" $out "*) strip -o "/tmp/t3/t3/$out" "$exe"; echo "   $out <- $exe" ;;
    esac
  done
  tar cJf .bint/tests3.tar.xz -C /tmp/t3 t3
fi

if [ ! -f .data/lego/transforms_train.json ]; then
  src=../shared/data/nerf_synthetic/lego
  [ -d "$src" ] || { echo "no $src: the lego scene cannot be copied (.data/lego is needed by h100_lego/final/render/coop)"; exit 1; }
  echo "== .data/lego: the train views and every 8th test view of $src"
  mkdir -p .data/lego/test
  cp "$src"/transforms_*.json .data/lego/
  cp -r "$src/train" .data/lego/
  for i in $(seq 0 8 199); do cp "$src/test/r_$i.png" .data/lego/test/; done
fi

# All 200 test views do not fit one call beside the training views: two halves, one per call of
# eval_half.sh after device_session.sh (each: its transforms_test.json and its 100 images).
for half in a b; do
  if [ ! -f ".eval_$half/lego/transforms_test.json" ]; then
    src=../shared/data/nerf_synthetic/lego
    [ -d "$src" ] || { echo "no $src: .eval_$half cannot be made"; exit 1; }
    echo "== .eval_$half/lego: half of the 200 test views of $src"
    mkdir -p ".eval_$half/lego/test"
    python3 - "$src" ".eval_$half/lego" "$half" <<'PY'
import json, shutil, sys
src, dst, half = sys.argv[1:4]
meta = json.load(open(f"{src}/transforms_test.json"))
frames = meta["frames"][:100] if half == "a" else meta["frames"][100:]
for f in frames:
    shutil.copy(f"{src}/{f['file_path']}.png", f"{dst}/{f['file_path']}.png")
meta["frames"] = frames
json.dump(meta, open(f"{dst}/transforms_test.json", "w"), indent=1)
PY
  fi
done

du -sh .gl .bin .bint .data .eval_a .eval_b 2>/dev/null
echo "carry what the script needs (h100_profile: .gl .bin; h100_final/render: .gl .bin .data;"
echo "h100_coop: .gl .bin .bint .data); the device tool takes 64 MiB in all."
