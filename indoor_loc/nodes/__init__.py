"""rclpy nodes: thin wrappers around pipeline stages. The only package that imports rclpy.

Every node process runs numpy's BLAS (OpenBLAS, from the numpy/scipy wheels) on one thread unless
``OPENBLAS_NUM_THREADS`` says otherwise: the stages multiply small matrices (a few particles' worth,
2x2 to 6x6 covariances) for which OpenBLAS's worker threads only wait, spinning, and that spinning was
a third of ``tll_pf``'s CPU time (docs/scaling.md). It is read when numpy loads, which is after this
package is imported (``python -m indoor_loc.nodes.<node>``), so it is set here. The results are the
same (test/test_node_blas_threads.py)."""
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
