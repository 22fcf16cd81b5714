"""Node processes run numpy's OpenBLAS on one thread (indoor_loc/nodes/__init__.py) unless the
environment says otherwise."""
from __future__ import annotations

import os
import subprocess
import sys

# the thread counts of the OpenBLAS libraries loaded (numpy's and scipy's wheels each bring one)
PROBE = ("import indoor_loc.nodes.tll_pf_node, numpy, scipy.linalg, ctypes\n"
         "libs = sorted({ln.split()[-1] for ln in open('/proc/self/maps') if 'openblas' in ln})\n"
         "for path in libs:\n"
         "    lib = ctypes.CDLL(path)\n"
         "    name = next(n for n in ('scipy_openblas_get_num_threads64_', 'scipy_openblas_get_num_threads',\n"
         "                            'openblas_get_num_threads') if hasattr(lib, n))\n"
         "    print(getattr(lib, name)())\n")


def _threads(env: dict) -> list[int]:
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return [int(v) for v in out.stdout.split()]


def test_nodes_run_blas_on_one_thread_unless_told():
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    got = _threads(env)
    assert got and set(got) == {1}, got
    assert set(_threads({**env, "OPENBLAS_NUM_THREADS": "2"})) == {2}
