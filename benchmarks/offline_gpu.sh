#!/usr/bin/env bash
# The renderer's tests and the GPU-relevant benchmarks on a machine without network access and without lodcast
# installed, such as a borrowed GPU box (benchmarks/offline_gpu.md says how the H200 run went).
#
#   bash benchmarks/offline_gpu.sh [--quick] WHEELS DATA OUT
#
# WHEELS  a folder of wheels for that machine's Python (what it lacks of lodcast's dependencies; "-" for none:
#         the Python in $PYTHON, default python3, has them all), installed into a temporary folder, never into
#         the system
# DATA    a folder with the real volumes (engine.nii.gz, ct_chest_dicom/), as ../shared/data
# OUT     where the logs, JUnit XML and JSON go
# --quick four test files and 256² benchmarks (a check of this script, a few minutes on two CPU cores)
#
# lodcast runs from this checkout: a temporary folder holds the package's top (lodcast/*.py) and links to store/,
# renderer/ and service/, first on PYTHONPATH, with PYTHONSAFEPATH=1 so that the checkout's own lodcast/ folder (the
# top alone) does not shadow it. NVIDIA's OpenCL driver, where its library is found, is named to the ICD loader of
# pyopencl's wheel in a vendors folder of its own (OCL_ICD_VENDORS), and LODCAST_DEVICE=gpu; else the first device.
set -euo pipefail
quick=0
if [ "${1:-}" = "--quick" ]; then quick=1; shift; fi
if [ $# -ne 3 ]; then
  echo "usage: bash benchmarks/offline_gpu.sh [--quick] WHEELS DATA OUT" >&2
  exit 2
fi
wheels=$1 data=$(cd "$2" && pwd) out=$(mkdir -p "$3" && cd "$3" && pwd)
repo=$(cd "$(dirname "$0")/.." && pwd)
py=${PYTHON:-python3}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
cd "$repo"
export PYTHONUNBUFFERED=1 PYTHONDONTWRITEBYTECODE=1 PYTHONSAFEPATH=1
if [ "$wheels" != "-" ]; then
  "$py" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target "$work/site" "$wheels"/*.whl
fi
mkdir -p "$work/pkg/lodcast"
cp lodcast/*.py lodcast/py.typed "$work/pkg/lodcast/"
for d in store renderer service; do ln -s "$repo/$d" "$work/pkg/lodcast/$d"; done
export PYTHONPATH="$work/pkg:$work/site${PYTHONPATH:+:$PYTHONPATH}"
export LODCAST_CACHE_DIR="$work/cache" LODCAST_SHARED_DATA="$data"
lib=""
for f in /usr/local/nvidia/lib64/libnvidia-opencl.so.1 /usr/lib/x86_64-linux-gnu/libnvidia-opencl.so.1 \
         /usr/lib64/libnvidia-opencl.so.1; do
  if [ -e "$f" ]; then lib=$f; break; fi
done
if [ -n "$lib" ]; then
  mkdir -p "$work/icd"
  echo "$lib" > "$work/icd/nvidia.icd"
  export OCL_ICD_VENDORS="$work/icd" LODCAST_DEVICE=gpu
fi
echo "NVIDIA OpenCL: ${lib:-not found}" | tee "$out/device.txt"
"$py" - <<'PY' | tee -a "$out/device.txt"
import sys

import numpy
import pyopencl as cl

from lodcast.opencl import Device

for p in cl.get_platforms():
    for d in p.get_devices():
        print(f"{p.name} ({p.version}): {d.name.strip()}, driver {d.driver_version}, {d.max_compute_units} compute "
              f"units, {d.global_mem_size >> 20} MiB, largest allocation {d.max_mem_alloc_size >> 20} MiB")
print("lodcast renders on:", Device().info(), "| Python", sys.version.split()[0], "| NumPy", numpy.__version__)
PY
tests=(adaptive_tf atlas_cells blend_modes distribution dual_tf ess_cells illumination_clip kernel_math
       kernel_numerics leap level_error lod_adaptive lod_cache lod_interblock lod_mask lod_render
       lod_selection_quality passes quality_report reference renderer_kernel renderer_output renderer_program
       renderer_scene renderer_structs renderer_tf screen_space selection significance visibility voxel_types)
sizes=(512 1024)
if [ $quick = 1 ]; then tests=(atlas_cells leap renderer_kernel kernel_math); sizes=(256); fi
files=()
for t in "${tests[@]}"; do files+=("tests/test_$t.py"); done
workers=$("$py" -c "import os; print(max(1, min(12, (os.cpu_count() or 2) - 2)))")
status=0
"$py" -m pytest -q -n "$workers" -p no:cacheprovider -rfE --junitxml="$out/tests.xml" "${files[@]}" \
  > "$out/tests.log" 2>&1 || status=$?
tail -n 25 "$out/tests.log"
"$py" benchmarks/bench_render.py --sizes "${sizes[@]}" --repeat 3 --json "$out/render.json" 2>&1 \
  | grep -v "CompilerWarning\|_prg.build" | tee "$out/render.txt"
"$py" benchmarks/bench_consistent_lod.py --sizes "${sizes[@]}" --repeat 3 --json "$out/consistent_lod.json" 2>&1 \
  | grep -v "CompilerWarning\|_prg.build" > "$out/consistent_lod.txt"
tail -n 3 "$out/consistent_lod.txt"
exit $status
