"""A scene build's statistics phase alone, on a built scene, in a process holding what
the build's earlier phases leave resident, under a 4 GiB limit; prints the phase's
time, the radii and the process's peak RSS. The 4K corner's whole build takes ~35 min;
this checks its last phase's memory in ~2 (2.06 GiB: resident at the phase's start,
sampled during a 4K build)::

    python benchmarks/scene_stats_memory.py /tmp/k4/T.zarr 2.06
"""
import resource, sys, time
import numpy as np
import bigT
from bigT.schedule.memory import resident_bytes, return_freed_memory
from bigT.scenes import statistics

sc = bigT.scenes.load(sys.argv[1])
held = float(sys.argv[2]) * 2**30
ballast = np.ones(max(0, int(held - resident_bytes())) // 8)  # touched: resident
return_freed_memory()
print(f"resident before the phase: {resident_bytes() / 2**30:.2f} GiB", flush=True)
t0 = time.perf_counter()
st = statistics.ground_truth_stats(sc.T, sc.A, sc.F, None, 4 << 30)
print(f"stats {time.perf_counter() - t0:.0f} s, rho_M {st.rho_M}, rho_A {st.rho_A}")
print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB")
