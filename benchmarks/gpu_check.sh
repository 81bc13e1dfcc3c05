#!/usr/bin/env bash
# The CUDA paths checked on a lent GPU machine in one short run (docs/benchmarks.md, "GPU"):
# the CUDA agreement tests, then the ALS and super-resolution benchmarks on the device.
# That machine has its own python3 with torch, numpy, scipy and OpenCV, and no Dask, Zarr or Prefect:
# btfcore (pure numerics) runs there from the source tree, without installing the project.
# Usage: benchmarks/gpu_check.sh OUT_DIR   (the results land in OUT_DIR as *.json and *.log)
set -uo pipefail
out=${1:?usage: benchmarks/gpu_check.sh OUT_DIR}
mkdir -p "$out"
cd "$(dirname "$0")/.."
export PYTHONPATH="$PWD:$PWD/benchmarks" PYTHONUNBUFFERED=1
python=${PYTHON:-python3}
{
    date -u
    nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv
    "$python" -c 'import torch, numpy, scipy, cv2; print("torch", torch.__version__, "cuda", torch.version.cuda,
        "numpy", numpy.__version__, "scipy", scipy.__version__, "opencv", cv2.__version__,
        "cpu threads", torch.get_num_threads())'
} 2>&1 | tee "$out/machine.log"
timeout 240 "$python" -m pytest -q -p no:cacheprovider --noconftest tests/btfcore/test_cuda.py 2>&1 | tee "$out/tests.log"
timeout 200 "$python" benchmarks/bench_als.py > "$out/als.json" 2> "$out/als.log"; echo "bench_als: exit $?"
timeout 200 "$python" benchmarks/bench_als.py --n-tx 65536 > "$out/als_65536.json" 2> "$out/als_65536.log"
echo "bench_als --n-tx 65536: exit $?"
timeout 200 "$python" benchmarks/bench_superres.py > "$out/superres.json" 2> "$out/superres.log"
echo "bench_superres: exit $?"
