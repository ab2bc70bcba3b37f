#!/usr/bin/env bash
# The cluster curve on a bigger machine: `bigT invert` of the dense full-HD corner on
# local threads and on local:N dask clusters (real worker processes, 1 thread each),
# each run's report kept so that, back on any machine,
#   python benchmarks/bench_scale.py --cluster-model --size "$size" --from-reports DIR
# checks the cluster model against them. A second call in the same WORKDIR adds the
# configurations the first left undone (the scene is built once).
#
#   bash benchmarks/cluster_curve.sh [WORKERS] [WORKDIR] [RUN_TIMEOUT_S]
#   e.g. bash benchmarks/cluster_curve.sh 16,8,4,2,1 bench-out/cluster-curve 200
#
# Where the machine cannot reach a package index, wheels in .whl/ are installed first
# (python3 -m pip download ... -d .whl dask distributed zarr numcodecs ...).
set -uo pipefail
workers=${1:-16,8,4,2,1}
workdir=${2:-bench-out/cluster-curve}
run_timeout=${3:-300}
size=${SIZE:-1080x1920}
wheels=${BIGT_WHEELS:-.whl}
if [ -d "$wheels" ]; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/bigT-site "$wheels"/*.whl || exit 1
    export PYTHONPATH=/tmp/bigT-site:$PWD
fi
export PYTHONUNBUFFERED=1 BIGT_BENCH_OUT=$workdir/out
python3 -c "import os, sys, numpy, numba, zarr, dask, distributed, bigT
print(sys.version.split()[0], 'cores', os.cpu_count(), 'numpy', numpy.__version__,
      'numba', numba.__version__, 'zarr', zarr.__version__, 'dask', dask.__version__)" || exit 1
# 64 GiB among the workers (local:N gives each 1/N); the scene build 16 GiB
mkdir -p "$workdir"
python3 benchmarks/bench_scale.py --cluster-model --size "$size" \
    --workers "$workers" --repeats 1 --workdir "$workdir" --memory-limit 64GiB \
    --scene-memory $((16 << 30)) --run-timeout "$run_timeout" --measure-only
