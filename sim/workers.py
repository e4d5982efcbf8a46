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

import concurrent.futures as cf
import contextlib
import ctypes
import multiprocessing as mp
import os
import signal
import sys

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


class WorkerPool:
    """Process pool of spawned, single-threaded workers that a kill cannot hang.

    Built on :class:`concurrent.futures.ProcessPoolExecutor` rather than
    ``multiprocessing.Pool``: a ``Pool`` whose worker dies while waiting for work (a SIGTERM
    sent to the whole process group by ``timeout`` or a scheduler, the OOM killer) leaves
    the task queue's lock held, and ``Pool.terminate`` then blocks forever; the parent
    never logs its run. The executor notices dead workers (``BrokenProcessPool``) and
    :meth:`__exit__` on an exception (Ctrl-C, SIGTERM turned into ``KeyboardInterrupt``)
    cancels what has not started and kills the workers at once, so finished results stay
    and the caller's ``finally`` blocks run.

    The environment of :func:`worker_environment` is set while the pool lives, because the
    executor spawns its workers on demand.
    """

    def __init__(self, processes: int, initializer=None, initargs=()):
        self._env = worker_environment()
        self._env.__enter__()
        try:
            self._executor = cf.ProcessPoolExecutor(
                processes,
                mp_context=mp.get_context("spawn"),
                initializer=_init_worker,
                initargs=(initializer, initargs),
            )
        except BaseException:
            self._env.__exit__(None, None, None)
            raise

    def __enter__(self) -> WorkerPool:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if exc_type is None:
                self._executor.shutdown(wait=True)
            else:
                self.kill()
        finally:
            self._env.__exit__(None, None, None)

    def kill(self) -> None:
        """Cancel pending work and SIGKILL the workers (finished results are kept)."""
        # the executor's own process table (private, hence the getattr): shutdown() alone
        # would wait for the running tasks
        processes = list((getattr(self._executor, "_processes", None) or {}).values())
        self._executor.shutdown(wait=False, cancel_futures=True)
        for proc in processes:
            with contextlib.suppress(Exception):
                proc.kill()
        for proc in processes:
            with contextlib.suppress(Exception):
                proc.join(timeout=10)

    def submit(self, fn, *args) -> cf.Future:
        """Start ``fn(*args)`` in a worker now; a Future (``.done()``, ``.result()``)."""
        return self._executor.submit(fn, *args)

    def apply(self, fn, *args):
        """``fn(*args)`` in a worker; its result."""
        return self._executor.submit(fn, *args).result()

    def imap_unordered(self, fn, iterable, chunksize: int = 1):
        """``fn(x)`` for each x, results in the order they finish (chunks of ``chunksize``)."""
        for future in cf.as_completed(self._submit_chunks(fn, iterable, chunksize)):
            yield from future.result()

    def map_async(self, fn, iterable, chunksize: int = 1) -> _MapResult:
        """Start ``fn(x)`` for each x now; ``.get()`` returns the results in order."""
        return _MapResult(self._submit_chunks(fn, iterable, chunksize))

    def _submit_chunks(self, fn, iterable, chunksize: int) -> list[cf.Future]:
        items = list(iterable)
        step = max(1, chunksize)
        return [
            self._executor.submit(_run_chunk, fn, items[i : i + step])
            for i in range(0, len(items), step)
        ]


class _MapResult:
    def __init__(self, futures):
        self._futures = futures

    def get(self) -> list:
        return [r for future in self._futures for r in future.result()]


def _init_worker(initializer, initargs) -> None:
    """Every worker: leave Ctrl-C and SIGTERM to the parent (which kills the workers, see
    :class:`WorkerPool`) and die with the parent (Linux), then the caller's initializer."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        # PR_SET_PDEATHSIG = 1: SIGKILL when the thread that spawned us exits (the pool is made
        # and fed from one thread, which outlives it)
        with contextlib.suppress(Exception):
            ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL, 0, 0, 0)
    if initializer is not None:
        initializer(*initargs)


def _run_chunk(fn, chunk) -> list:
    return [fn(x) for x in chunk]


def spawn_pool(processes: int, initializer=None, initargs=()) -> WorkerPool:
    """Pool of ``processes`` spawned workers that start single-threaded (module docstring);
    use it as a context manager."""
    return WorkerPool(processes, initializer, initargs)
