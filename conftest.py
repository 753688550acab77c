"""Test-session settings shared by every test (loaded by pytest before any test module).

Single-threaded BLAS/OpenMP: the suite runs many small linear-algebra calls, which
multi-threaded OpenBLAS slows down badly on a shared 2-core machine (measured: 318 s
vs 19 s for the identification tests).  Set before numpy is imported.
"""

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
