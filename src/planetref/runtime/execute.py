"""Executors of per-tile work: in process, a local process pool, or a Dask cluster.

Matching is embarrassingly parallel over tiles. An executor runs one picklable task
function over a list of small task descriptions and yields each outcome as it finishes:

* :class:`InProcessExecutor` — one tile after another in this process (the default).
* :class:`LocalPoolExecutor` — a :class:`concurrent.futures.ProcessPoolExecutor` of
  ``n_workers`` processes (a failed task is resubmitted once).
* :class:`DaskExecutor` — a ``dask.distributed`` cluster at ``tcp://HOST:PORT``, or a
  :class:`distributed.LocalCluster` started for the run (``dask-local:N``) and closed
  after it (a failed or lost task is retried twice).

:func:`make_executor` builds one from a spec string (the CLI's ``--scheduler``).

The executors are generic: they know nothing of tiles or matchers. The tile tasks they
run for the front end (small picklable descriptions, never arrays or matcher instances)
are in :mod:`planetref.frontend.tasks`.
"""

from __future__ import annotations

import os
import re
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from planetref.errors import InputError

__all__ = [
    "CONNECT_TIMEOUT_S",
    "HEARTBEAT_S",
    "MAX_WORKERS",
    "SCHEDULER_HELP",
    "DaskExecutor",
    "Executor",
    "InProcessExecutor",
    "LocalPoolExecutor",
    "SchedulerError",
    "SchedulerSpec",
    "TaskOutcome",
    "make_executor",
    "parse_scheduler",
]

SCHEDULER_HELP = "inprocess (default), pool:N, dask-local:N, or tcp://HOST:PORT[?timeout=SECONDS]"
CONNECT_TIMEOUT_S = 10.0
"""Default time to connect to a Dask scheduler (seconds)."""
MAX_WORKERS = 4096
"""Most workers ``pool:N`` and ``dask-local:N`` accept."""


class SchedulerError(InputError):
    """A ``--scheduler`` that cannot be reached (refused, no answer within the timeout)."""


# --------------------------------------------------------------------------- executors


@dataclass
class TaskOutcome:
    """One finished task.

    Attributes:
        index: Position of the task in the submitted list.
        result: What the task function returned (None when it failed).
        error: The exception of a task that failed for good (after the retries).
    """

    index: int
    result: Any = None
    error: BaseException | None = None


class Executor:
    """Runs a task function over task descriptions, yielding outcomes as they finish.

    Executors are context managers; resources (processes, a cluster) start on first use
    and stop on :meth:`close`. One executor may serve several runs.
    """

    name = "executor"
    parallel = True

    def map_unordered(
        self, fn: Callable[[Any], Any], tasks: Sequence[Any]
    ) -> Iterator[TaskOutcome]:
        """Run ``fn`` on every task; yield a :class:`TaskOutcome` per task, in finishing order."""
        raise NotImplementedError

    def close(self) -> None:
        """Release the workers (idempotent)."""

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r})"


class InProcessExecutor(Executor):
    """Everything in this process, one task after another (today's behaviour)."""

    name = "inprocess"
    parallel = False

    def map_unordered(
        self, fn: Callable[[Any], Any], tasks: Sequence[Any]
    ) -> Iterator[TaskOutcome]:
        """Run the tasks in order, here."""
        for i, task in enumerate(tasks):
            try:
                yield TaskOutcome(i, result=fn(task))
            except Exception as exc:
                yield TaskOutcome(i, error=exc)


#: How often a pool worker checks that the process that started it is alive (seconds).
HEARTBEAT_S = 0.5


def parent_alive(parent_pid: int) -> bool:
    """Whether this process's parent is still ``parent_pid`` (not re-parented to init)."""
    return os.getppid() == parent_pid


def bind_to_parent(parent_pid: int, *, death_signal: bool = True) -> None:
    """Make a pool worker belong to the run that started it (the pool's initializer).

    Args:
        parent_pid: The run's process.
        death_signal: Also ask the kernel for the death signal (a process started from
            a thread that may end before the run should pass False: the signal follows
            the thread that started the worker, not the process).

    * Linux: ``PR_SET_PDEATHSIG`` asks the kernel to SIGKILL the worker when its parent
      dies (SIGKILL, SIGTERM or a crash of the run), so no worker outlives it.
    * Everywhere: a daemon thread checks every :data:`HEARTBEAT_S` seconds that the
      parent is alive and ends the worker at once otherwise (the death signal is tied
      to the thread that started the worker; the heartbeat is not).
    * Ctrl-C reaches the whole terminal process group: the worker ignores SIGINT, the
      parent stops the pool (no KeyboardInterrupt traceback from every worker).
    """
    import signal
    import sys
    import threading

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if death_signal and sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG = 1
        except (OSError, AttributeError):
            pass  # the heartbeat below still ends the worker
    if not parent_alive(parent_pid):  # the parent died before the signal was armed
        os._exit(1)

    def heartbeat() -> None:
        while parent_alive(parent_pid):
            time.sleep(HEARTBEAT_S)
        os._exit(1)

    threading.Thread(target=heartbeat, name="planetref-parent-heartbeat", daemon=True).start()


class LocalPoolExecutor(Executor):
    """A local pool of ``n_workers`` processes (spawned, so safe with torch and OpenCV).

    A task that fails (an exception, or its process dying) is resubmitted once; a broken
    pool is replaced first.
    """

    def __init__(self, n_workers: int) -> None:
        if n_workers < 1:
            raise InputError(f"pool needs at least one worker, got {n_workers}")
        self.n_workers = int(n_workers)
        self.name = f"pool:{self.n_workers}"
        self._pool: Any = None

    def _get_pool(self) -> Any:
        if self._pool is None:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            self._pool = ProcessPoolExecutor(
                max_workers=self.n_workers,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=bind_to_parent,
                initargs=(os.getpid(),),
            )
        return self._pool

    def map_unordered(
        self, fn: Callable[[Any], Any], tasks: Sequence[Any]
    ) -> Iterator[TaskOutcome]:
        """Submit every task, yield outcomes as they complete, resubmit a failure once."""
        from concurrent.futures import FIRST_COMPLETED, wait
        from concurrent.futures.process import BrokenProcessPool

        pool = self._get_pool()
        running = {pool.submit(fn, t): (i, 0) for i, t in enumerate(tasks)}
        while running:
            finished, _ = wait(list(running), return_when=FIRST_COMPLETED)
            for fut in finished:
                i, tries = running.pop(fut)
                exc = fut.exception()
                if exc is None:
                    yield TaskOutcome(i, result=fut.result())
                elif tries < 1:
                    if isinstance(exc, BrokenProcessPool):
                        self._replace_broken_pool()
                    running[self._get_pool().submit(fn, tasks[i])] = (i, tries + 1)
                else:
                    yield TaskOutcome(i, error=exc)

    def _replace_broken_pool(self) -> None:
        pool = self._pool
        if pool is not None and getattr(pool, "_broken", False):
            pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    def close(self) -> None:
        """Shut the pool down."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


class DaskExecutor(Executor):
    """Tasks on a ``dask.distributed`` cluster.

    Args:
        address: ``tcp://HOST:PORT`` of a running scheduler, or ``dask-local:N`` to start
            a :class:`distributed.LocalCluster` of ``N`` single-threaded worker processes
            on the loopback interface for as long as the executor lives.
        retries: How often a failed or lost task is retried.
    """

    def __init__(
        self, address: str, *, retries: int = 2, connect_timeout_s: float = CONNECT_TIMEOUT_S
    ) -> None:
        self.address = address
        self.name = address
        self.retries = int(retries)
        self.connect_timeout_s = float(connect_timeout_s)
        self._cluster: Any = None
        self._client: Any = None

    @property
    def client(self) -> Any:
        """The :class:`distributed.Client` (connects, or starts the local cluster, lazily)."""
        if self._client is None:
            from distributed import Client, LocalCluster

            m = re.fullmatch(r"dask-local:(\d+)", self.address)
            if m:
                self._cluster = LocalCluster(
                    n_workers=int(m.group(1)),
                    threads_per_worker=1,
                    processes=True,
                    host="127.0.0.1",
                    dashboard_address=None,
                )
                self._client = Client(self._cluster)
            else:
                self._client = self._connect(Client)
        return self._client

    def _connect(self, client_cls: Any) -> Any:
        """Connect to ``tcp://HOST:PORT`` within ``connect_timeout_s``, or say why not."""
        import socket

        m = re.fullmatch(r"tcp://\[?([^\]]+?)\]?:(\d+)", self.address)
        host, port = (m.group(1), int(m.group(2))) if m else ("", 0)
        where = f"the Dask scheduler {self.address}"
        hint = f"(set the timeout with {self.address}?timeout=SECONDS)"
        try:  # a refused or unroutable port fails here at once, not after retries
            probe = socket.create_connection((host, port), timeout=self.connect_timeout_s)
        except TimeoutError:
            raise SchedulerError(
                f"cannot connect to {where} within {self.connect_timeout_s:g} s {hint}"
            ) from None
        except OSError as exc:
            raise SchedulerError(
                f"cannot connect to {where} ({exc.strerror or type(exc).__name__}); "
                "is the scheduler running?"
            ) from None
        # A Dask scheduler sends its handshake as soon as it accepts a connection; a
        # listener that never speaks would otherwise hang the client forever.
        with probe:
            try:
                probe.settimeout(self.connect_timeout_s)
                greeting = probe.recv(1)
            except TimeoutError:
                greeting = None
            except OSError:
                greeting = b""
        if not greeting:
            what = "no answer" if greeting is None else "the connection was closed"
            raise SchedulerError(
                f"{what} from {where} within {self.connect_timeout_s:g} s; is it a Dask "
                f"scheduler? {hint}"
            )
        try:
            return client_cls(self.address, timeout=self.connect_timeout_s, set_as_default=False)
        except (OSError, TimeoutError) as exc:
            raise SchedulerError(
                f"no answer from {where} within {self.connect_timeout_s:g} s "
                f"({type(exc).__name__}); is it a Dask scheduler? {hint}"
            ) from None

    def map_unordered(
        self, fn: Callable[[Any], Any], tasks: Sequence[Any]
    ) -> Iterator[TaskOutcome]:
        """Submit every task (``retries``), yield outcomes with ``as_completed``."""
        from distributed import as_completed

        client = self.client
        futures = {
            client.submit(fn, t, retries=self.retries, pure=False): i for i, t in enumerate(tasks)
        }
        try:
            for fut in as_completed(list(futures)):
                i = futures[fut]
                try:
                    yield TaskOutcome(i, result=fut.result())
                except Exception as exc:
                    yield TaskOutcome(i, error=exc)
                fut.release()
        finally:
            client.cancel([f for f in futures if not f.done()])

    def close(self) -> None:
        """Close the client, and the local cluster when this executor started it."""
        if self._client is not None:
            self._client.close()
            self._client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None


@dataclass(frozen=True)
class SchedulerSpec:
    """A ``--scheduler`` spec, parsed once (:func:`parse_scheduler`).

    Attributes:
        kind: ``"inprocess"``, ``"pool"``, ``"dask-local"`` or ``"tcp"``.
        workers: Worker processes started on this machine (``pool``/``dask-local``), else 0.
        address: ``tcp://HOST:PORT`` of a running Dask scheduler (``tcp`` only).
        timeout_s: Connection timeout of a ``tcp`` scheduler (seconds).
    """

    kind: str = "inprocess"
    workers: int = 0
    address: str | None = None
    timeout_s: float = CONNECT_TIMEOUT_S

    @property
    def local_workers(self) -> int:
        """Worker processes the spec starts on this machine (0: none or remote)."""
        return self.workers if self.kind in ("pool", "dask-local") else 0

    def executor(self) -> Executor:
        """A new executor of this kind (nothing is started until it is first used)."""
        if self.kind == "pool":
            return LocalPoolExecutor(self.workers)
        if self.kind == "dask-local":
            return DaskExecutor(f"dask-local:{self.workers}")
        if self.kind == "tcp":
            return DaskExecutor(str(self.address), connect_timeout_s=self.timeout_s)
        return InProcessExecutor()


def parse_scheduler(spec: str | SchedulerSpec | None) -> SchedulerSpec:
    """Parse a ``--scheduler`` spec (the one parser of it).

    Args:
        spec: None or ``"inprocess"``; ``"pool:N"``; ``"dask-local:N"`` (N from 1 to
            :data:`MAX_WORKERS`); ``"tcp://HOST:PORT"`` (port 1-65535), optionally with
            ``?timeout=SECONDS`` (connection timeout, default :data:`CONNECT_TIMEOUT_S`);
            or a parsed spec (returned as is).

    Raises:
        InputError: Any other spec (the message lists the valid forms), a worker count or
            port out of range.
    """
    if isinstance(spec, SchedulerSpec):
        return spec
    s = "" if spec is None else str(spec).strip()
    if s.lower() in ("", "inprocess", "in-process"):
        return SchedulerSpec()
    m = re.fullmatch(r"(pool|dask-local):(\d{1,12})", s)
    if m:
        n = int(m.group(2))
        if not 1 <= n <= MAX_WORKERS:
            raise InputError(
                f"{m.group(1)}:N needs 1 <= N <= {MAX_WORKERS} workers, got {n}; "
                f"valid: {SCHEDULER_HELP}",
                field="scheduler",
            )
        return SchedulerSpec(m.group(1), n)
    m = re.fullmatch(
        r"(tcp://(?:[^\s:/?\[\]]+|\[[0-9A-Fa-f:.]+\]):(\d{1,12}))/?(?:\?timeout=([^&\s]+))?", s
    )
    if m:
        port = int(m.group(2))
        if not 1 <= port <= 65535:
            raise InputError(f"port {port} is outside 1-65535 in {spec!r}", field="scheduler")
        timeout = CONNECT_TIMEOUT_S
        if m.group(3) is not None:
            try:
                timeout = float(m.group(3))
            except ValueError:
                timeout = float("nan")
            if not 0 < timeout <= 3600:
                raise InputError(
                    f"timeout={m.group(3)} must be a number of seconds in (0, 3600]",
                    field="scheduler",
                )
        return SchedulerSpec("tcp", 0, m.group(1), timeout)
    raise InputError(
        f"unknown scheduler {spec!r}; valid: {SCHEDULER_HELP} (N a positive integer)",
        field="scheduler",
    )


def make_executor(spec: str | SchedulerSpec | Executor | None) -> Executor:
    """An executor from a ``--scheduler`` spec (see :func:`parse_scheduler`).

    Returns:
        The executor given, or a new one of the spec's kind (nothing is started until it
        is first used).

    Raises:
        InputError: An invalid spec (one line).
    """
    if isinstance(spec, Executor):
        return spec
    return parse_scheduler(spec).executor()
