#!/usr/bin/env bash
# Pack mitsuba, drjit, OpenEXR and trimesh for a bare GPU machine (the device tool's), as one .tar.xz
# that scripts/gpu_check.sh unpacks onto PYTHONPATH:
#
#   bash scripts/gpu_site.sh [OUT_DIR] [PYTHON_VERSION]      # defaults: .whl_dev, 3.12
#
# Only the rgb variants' extension modules are kept (the spectral, mono and polarized ones are
# ~30 MB the check never loads), with the headers, CMake files and the sunsky data: ~35 MB
# packed, inside the device tool's 64 MiB. OUT_DIR also gets a copy of the shared data (probes
# and MERL-NBRDF tables) and the benchmark sphere (input/), for `gpu_check.sh`'s recover check.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
OUT_DIR="$(mkdir -p "${1:-.whl_dev}" && cd "${1:-.whl_dev}" && pwd)"
PYV="${2:-3.12}"
PY=.venv/bin/python   # scripts/run.sh setup makes it; the versions to pack are the ones tested here
MITSUBA="$("$PY" -c 'import importlib.metadata as m; print(m.version("mitsuba"))')"
DRJIT="$("$PY" -c 'import importlib.metadata as m; print(m.version("drjit"))')"
wheels="$(mktemp -d)"; site="$(mktemp -d)"
trap 'rm -rf "$wheels" "$site"' EXIT
for pkg in "mitsuba==$MITSUBA" "drjit==$DRJIT" OpenEXR trimesh; do
    python3 -m pip download -q --no-deps --only-binary=:all: --python-version "$PYV" --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
        --platform manylinux2014_x86_64 -d "$wheels" "$pkg"
done
for w in "$wheels"/*.whl; do (cd "$site" && python3 -m zipfile -e "$w" .); done
(cd "$site/mitsuba" && ls ./*_ad_*.cpython*.so ./scalar_*.cpython*.so | grep -v -E '/(cuda_ad_rgb|llvm_ad_rgb|scalar_rgb)\.' \
    | xargs rm -f && rm -rf include data/sunsky cmake)
find "$site" -name '*.pyi' -delete
mkdir -p "$OUT_DIR/input"
tar -cJf "$OUT_DIR/site.tar.xz" -C "$site" .
DATA="${MI_BIVARIATE_DATA:-../shared/data}"
rm -rf "$OUT_DIR/data" && cp -r "$DATA" "$OUT_DIR/data" && chmod -R u+w "$OUT_DIR/data"
(cd benchmarks && MI_BIVARIATE_DATA="$OUT_DIR/data" "../$PY" - "$OUT_DIR" <<'PY'
import sys
import bench_speed
from mi_bivariate.images import write_exr
from mi_bivariate.variants import ensure_variant

ensure_variant("llvm_ad_rgb")
_, probe, shot = bench_speed.load_inputs()
write_exr(f"{sys.argv[1]}/input/sphere.exr", shot.image)
probe.save_exr(f"{sys.argv[1]}/input/probe.exr")
PY
)
du -sh "$OUT_DIR"
