"""One thread budget for torch, OpenCV and BLAS, per process and per worker.

Torch, OpenCV and the BLAS under numpy each start as many threads as there are cores.
Together in one process (and again in every worker process of a pool), they oversubscribe
a small machine: on 2 busy cores a 2 ms least-squares solve took 214 ms with BLAS
threads fighting torch's. The policy here:

- the main process gets ``threads`` threads (``--threads``, default: the cores this
  process may use) for torch and OpenCV, and for BLAS;
- each of ``n_workers`` workers gets ``max(1, threads // n_workers)``;
- the many small dense solves of the adjustment, the RPC refits and the report run with
  a single-threaded BLAS (:func:`single_threaded_blas`).

BLAS threads are limited through threadpoolctl when it is installed, otherwise through
OpenBLAS's own entry points (see :mod:`planetref.runtime.blas`); OpenMP-based libraries
read ``OMP_NUM_THREADS``, which is set for child processes started afterwards.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass

from planetref.errors import InputError
from planetref.runtime.blas import single_threaded_blas

__all__ = [
    "ThreadBudget",
    "apply_thread_budget",
    "available_cores",
    "compute_threads",
    "single_threaded_blas",
    "worker_threads",
]

_ENV_VARS = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "OPENCV_FOR_THREADS_NUM",
)


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity where the OS tells, else the count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


def compute_threads(requested: int | None = None) -> int:
    """Threads of planetref's own compiled kernels (the adjustment's chunk pool).

    ``requested`` when given; otherwise ``OMP_NUM_THREADS`` when set (what
    :func:`apply_thread_budget` grants each process: ``--threads 1`` means one thread,
    and a pool worker gets its share), else the cores this process may use.
    """
    if requested is not None:
        if requested < 1:
            raise InputError(f"threads must be >= 1, got {requested}", field="threads")
        return int(requested)
    env = os.environ.get("OMP_NUM_THREADS", "").strip()
    if env.isdigit() and int(env) >= 1:
        return min(int(env), available_cores())
    return available_cores()


def worker_threads(threads: int, n_workers: int) -> int:
    """Threads of each of ``n_workers`` workers sharing ``threads`` (at least one)."""
    if threads < 1 or n_workers < 1:
        raise InputError(f"threads and workers must be >= 1, got {threads} and {n_workers}")
    return max(1, threads // n_workers)


@dataclass(frozen=True)
class ThreadBudget:
    """Threads granted to this process and to each worker process it starts.

    Attributes:
        threads: Threads of torch, OpenCV and BLAS in this process.
        per_worker: Threads of each worker process (pool or local Dask workers).
    """

    threads: int
    per_worker: int

    def __post_init__(self) -> None:
        if self.threads < 1 or self.per_worker < 1:
            raise InputError(f"--threads must be >= 1, got {self.threads}", field="threads")

    @classmethod
    def resolve(cls, threads: int | None, n_workers: int = 0) -> ThreadBudget:
        """The budget for ``threads`` in all (default: the cores) and ``n_workers`` workers."""
        total = available_cores() if threads is None else int(threads)
        if total < 1:
            raise InputError(f"--threads must be >= 1, got {total}", field="threads")
        return cls(total, worker_threads(total, n_workers) if n_workers > 0 else total)


def _limit_blas(n: int) -> None:
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        from planetref.runtime import blas as _blas

        for _getter, setter in _blas._openblas():
            with contextlib.suppress(OSError, ValueError):
                setter(n)  # type: ignore[operator]
        return
    threadpool_limits(limits=n, user_api="blas")


def apply_thread_budget(budget: ThreadBudget) -> ThreadBudget:
    """Apply a budget: torch, OpenCV and BLAS of this process; the environment of workers.

    Worker processes started afterwards (spawned pool workers, local Dask workers) inherit
    ``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS``, ``MKL_NUM_THREADS`` and
    ``OPENCV_FOR_THREADS_NUM`` set to ``budget.per_worker``, which torch, the BLAS and
    OpenCV read when they start. Remote Dask workers keep their own settings.

    Returns:
        The budget (for chaining).
    """
    for var in _ENV_VARS:
        os.environ[var] = str(budget.per_worker)
    n = budget.threads
    import cv2
    import torch

    torch.set_num_threads(n)
    cv2.setNumThreads(n)
    _limit_blas(n)
    return budget
