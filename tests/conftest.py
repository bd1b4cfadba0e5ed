"""Shared test set-up.

The design and robustness checks solve hundreds of small eigenvalue problems; on the shared 2-core machine
OpenBLAS threads only contend for them (8 ms per 110-state problem with one thread, ~120 ms with two), so the
tests run BLAS single-threaded unless the environment says otherwise (set before numpy is first imported)."""
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
