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
# 20 iterations per figure: on a GPU an iteration (~0.1 s) is far below the set-up's run-to-run noise, and
# rank-128 data keeps the rank-64 fit improving for that long (docs/benchmarks.md, "the CUDA paths")
for mb in 256 4096; do
    timeout 200 "$python" benchmarks/bench_als.py --n-tx 65536 --iterations 21 --data-rank 128 --chunk-mb $mb \
        > "$out/als_chunk$mb.json" 2> "$out/als_chunk$mb.log"
    echo "bench_als --chunk-mb $mb: exit $?"
done
timeout 200 "$python" benchmarks/bench_superres.py > "$out/superres.json" 2> "$out/superres.log"
echo "bench_superres: exit $?"
