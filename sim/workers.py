"""Process pools of single-threaded workers.

The dataset jobs (generation, derive) run one process per core. Each process would
otherwise start its own thread pools sized to the whole machine (OpenBLAS / MKL / OpenMP
in NumPy and SciPy, XLA's CPU client if JAX computes anything), so 16 workers on 16 cores
could run hundreds of threads that contend for the cores. :func:`spawn_pool` starts the
workers with those pools set to one thread (environment variables read at import in the
child). ``OMNIHANG_WORKER_THREADS=N`` sets N instead; ``0`` leaves the libraries' defaults
(to measure the difference).
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os

THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
# XLA CPU: no multi-threaded Eigen (the only XLA_FLAGS knob for the intra-op pool;
# TF's intra_op_parallelism_threads is not an XLA flag)
XLA_ONE_THREAD = "--xla_cpu_multi_thread_eigen=false"


@contextlib.contextmanager
def worker_environment():
    """Environment for spawned workers: one thread per library pool (see module)."""
    n = int(os.environ.get("OMNIHANG_WORKER_THREADS", "1"))
    saved = {k: os.environ.get(k) for k in (*THREAD_VARS, "XLA_FLAGS")}
    try:
        if n > 0:
            for k in THREAD_VARS:
                os.environ[k] = str(n)
            if n == 1:
                os.environ["XLA_FLAGS"] = f"{saved['XLA_FLAGS'] or ''} {XLA_ONE_THREAD}".strip()
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def thread_settings() -> dict:
    """This process's thread settings (the variables of the module docstring)."""
    return {k: os.environ.get(k) for k in (*THREAD_VARS, "XLA_FLAGS")}


def spawn_pool(processes: int, initializer=None, initargs=()):
    """``multiprocessing`` spawn pool whose workers start single-threaded (module)."""
    with worker_environment():
        return mp.get_context("spawn").Pool(processes, initializer, initargs)
