"""The application layer: the ``iptm`` command line, the main job, the report, the dashboard's helpers and
the benchmarks. It holds no physics or numerics of its own.

Importing it sets one process-wide runtime default, as applications (not libraries) do: numba's OpenMP
threads wait passively at barriers (``OMP_WAIT_POLICY=PASSIVE``). The DP kernels hit one or two
barriers per time step, and on a shared 2-core machine active spinning made the 2-thread Thermal-DP
backward pass ten times slower than one thread. An explicit user setting wins.
"""
import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
