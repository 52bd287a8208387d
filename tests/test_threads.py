"""The thread budget: per-process and per-worker counts, and applying them."""

from __future__ import annotations

import os

import pytest

from planetref.errors import InputError
from planetref.runtime.execute import SchedulerSpec, make_executor, parse_scheduler
from planetref.runtime.threads import (
    ThreadBudget,
    apply_thread_budget,
    available_cores,
    worker_threads,
)


def test_worker_share_and_scheduler_parsing():
    assert worker_threads(16, 4) == 4
    assert worker_threads(2, 4) == 1  # never zero: oversubscription is bounded at 1 each
    assert parse_scheduler("pool:3").local_workers == 3
    assert parse_scheduler("dask-local:2").local_workers == 2
    tcp = parse_scheduler("tcp://127.0.0.1:8786?timeout=5")
    assert (tcp.kind, tcp.local_workers, tcp.address, tcp.timeout_s) == (
        "tcp",
        0,
        "tcp://127.0.0.1:8786",
        5.0,
    )
    assert parse_scheduler(None) == SchedulerSpec() and SchedulerSpec().local_workers == 0
    # One parser: a parsed spec passes through unchanged, an executor is built from it.
    spec = parse_scheduler("pool:2")
    assert parse_scheduler(spec) is spec
    assert make_executor(spec).name == "pool:2"
    with pytest.raises(InputError, match="unknown scheduler"):
        parse_scheduler("pool")
    b = ThreadBudget.resolve(8, 3)
    assert (b.threads, b.per_worker) == (8, 2)
    assert ThreadBudget.resolve(None).threads == available_cores()
    with pytest.raises(InputError):
        ThreadBudget.resolve(0)


def test_apply_sets_torch_opencv_blas_and_worker_environment(monkeypatch):
    import cv2
    import torch

    from planetref.runtime.blas import _openblas

    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        if var in os.environ:  # restored by monkeypatch after the test
            monkeypatch.setenv(var, os.environ[var])
        else:
            monkeypatch.delenv(var, raising=False)
    monkeypatch.delenv("OPENCV_FOR_THREADS_NUM", raising=False)
    saved = (torch.get_num_threads(), cv2.getNumThreads())
    blas = [(getter, setter, getter()) for getter, setter in _openblas()]
    try:
        apply_thread_budget(ThreadBudget(threads=1, per_worker=1))
        assert torch.get_num_threads() == 1
        assert cv2.getNumThreads() == 1
        assert all(getter() == 1 for getter, _, _ in blas)
        assert os.environ["OMP_NUM_THREADS"] == "1"
    finally:
        torch.set_num_threads(saved[0])
        cv2.setNumThreads(saved[1])
        for _, setter, n in blas:
            setter(n)
