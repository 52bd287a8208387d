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

Tasks carry only descriptions (file paths, the tile, the front-end settings, the matcher
name and options, see :class:`TileSources`), never arrays: each worker process opens the
rasters, the camera and the DEM and builds the matchers once, and caches them
(:func:`_worker_context`) for every later tile of the same strip.
"""

from __future__ import annotations

import functools
import json
import re
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

from planetref.errors import InputError

__all__ = [
    "CONNECT_TIMEOUT_S",
    "MAX_WORKERS",
    "SCHEDULER_HELP",
    "DaskExecutor",
    "Executor",
    "InProcessExecutor",
    "LocalPoolExecutor",
    "SchedulerError",
    "TaskOutcome",
    "TileSources",
    "make_executor",
    "run_tile_task",
]

SCHEDULER_HELP = "inprocess (default), pool:N, dask-local:N, or tcp://HOST:PORT[?timeout=SECONDS]"
CONNECT_TIMEOUT_S = 10.0
"""Default time to connect to a Dask scheduler (seconds)."""
MAX_WORKERS = 4096
"""Most workers ``pool:N`` and ``dask-local:N`` accept."""


class SchedulerError(InputError):
    """A ``--scheduler`` that cannot be reached (refused, no answer within the timeout)."""


# --------------------------------------------------------------------------- tasks


@dataclass(frozen=True)
class TileSources:
    """Where a worker finds everything a strip's tiles need (paths and names only).

    Attributes:
        camera: Camera file of the strip (all its CCDs).
        images: ``(ccd, path)`` of each CCD image, CCD names as the camera knows them.
        ref: Reference orthoimage path.
        dem: Reference DEM (GeoTIFF) path.
        matcher: Registry name of the matcher.
        ref_band: Band of the reference orthoimage.
        dem_band: Band of the DEM.
        matcher_options: Keyword options of the fine-stage matcher.
        coarse_options: Keyword options of the coarse-stage matcher; None: the fine
            matcher serves both stages.
        weights_dir: Folder of pretrained weights (learned matchers).
    """

    camera: str
    images: tuple[tuple[str, str], ...]
    ref: str
    dem: str
    matcher: str
    ref_band: int = 1
    dem_band: int = 1
    matcher_options: Mapping[str, Any] = field(default_factory=dict)
    coarse_options: Mapping[str, Any] | None = None
    weights_dir: str | None = None

    def key(self) -> str:
        """A canonical JSON text of the sources (the worker cache key)."""
        doc = asdict(self)
        doc["images"] = [list(p) for p in self.images]
        return json.dumps(doc, sort_keys=True, default=str)


@dataclass
class _WorkerContext:
    camera: Any
    images: dict[str, Any]
    ref: Any
    dem: Any
    fine: Any
    coarse: Any


@functools.lru_cache(maxsize=4)
def _worker_context(key: str) -> _WorkerContext:
    """Open a strip's rasters, camera and DEM and build its matchers, once per process."""
    from planetref.camera.io import load_camera
    from planetref.matching.registry import get_matcher
    from planetref.raster.dem import GridTerrain
    from planetref.raster.image import CcdImage
    from planetref.raster.ortho import ReferenceOrtho

    doc = json.loads(key)
    fine = get_matcher(doc["matcher"], weights_dir=doc["weights_dir"], **doc["matcher_options"])
    coarse = (
        fine
        if doc["coarse_options"] is None
        else get_matcher(doc["matcher"], weights_dir=doc["weights_dir"], **doc["coarse_options"])
    )
    return _WorkerContext(
        camera=load_camera(doc["camera"]),
        images={ccd: CcdImage(path) for ccd, path in doc["images"]},
        ref=ReferenceOrtho(doc["ref"], band=int(doc["ref_band"])),
        dem=GridTerrain.from_geotiff(doc["dem"], band=int(doc["dem_band"])),
        fine=fine,
        coarse=coarse,
    )


def run_tile_task(task: Mapping[str, Any]) -> dict[str, Any]:
    """Match one tile in a worker (the task function of every executor).

    Args:
        task: ``{"sources": TileSources.key(), "tile": Tile.to_dict(), "config":
            FrontendConfig.model_dump(), "ratio": float | None, "raise_errors": bool}``.

    Returns:
        The tile's :meth:`~planetref.frontend.match_tile.TileResult.to_dict`. An exception
        of the matching itself becomes status ``error`` (as in process) unless
        ``raise_errors``; failing to open the inputs raises (and the task is retried).
    """
    from planetref.frontend.config import FrontendConfig
    from planetref.frontend.match_tile import TileResult, match_tile
    from planetref.frontend.tiles import Tile

    ctx = _worker_context(task["sources"])
    cfg = FrontendConfig.model_validate(task["config"])
    tile = Tile.from_dict(task["tile"])
    try:
        res = match_tile(
            tile,
            image=ctx.images[tile.ccd],
            camera=ctx.camera,
            ref=ctx.ref,
            terrain=ctx.dem,
            matcher=ctx.fine,
            config=cfg,
            ratio=task["ratio"],
            coarse_matcher=ctx.coarse,
        )
    except Exception as exc:
        if task.get("raise_errors"):
            raise
        name = str(getattr(ctx.fine, "name", type(ctx.fine).__name__))
        res = TileResult(
            tile=tile,
            matcher=name,
            status="error",
            message=f"{type(exc).__name__}: {exc}",
            geometry=cfg.geometry,
        )
    return res.to_dict()


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
                max_workers=self.n_workers, mp_context=multiprocessing.get_context("spawn")
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


def make_executor(spec: str | Executor | None) -> Executor:
    """An executor from a ``--scheduler`` spec.

    Args:
        spec: None or ``"inprocess"``; ``"pool:N"``; ``"dask-local:N"`` (N from 1 to
            :data:`MAX_WORKERS`); ``"tcp://HOST:PORT"`` (port 1-65535), optionally with
            ``?timeout=SECONDS`` (connection timeout, default :data:`CONNECT_TIMEOUT_S`);
            or an executor (returned as is).

    Returns:
        The executor (nothing is started until it is first used).

    Raises:
        InputError: Any other spec (the message lists the valid forms), a worker count or
            port out of range.
    """
    if spec is None or isinstance(spec, Executor):
        return spec or InProcessExecutor()
    s = str(spec).strip()
    if s.lower() in ("", "inprocess", "in-process"):
        return InProcessExecutor()
    m = re.fullmatch(r"(pool|dask-local):(\d{1,12})", s)
    if m:
        n = int(m.group(2))
        if not 1 <= n <= MAX_WORKERS:
            raise InputError(
                f"{m.group(1)}:N needs 1 <= N <= {MAX_WORKERS} workers, got {n}; "
                f"valid: {SCHEDULER_HELP}",
                field="scheduler",
            )
        return LocalPoolExecutor(n) if m.group(1) == "pool" else DaskExecutor(f"dask-local:{n}")
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
        return DaskExecutor(m.group(1), connect_timeout_s=timeout)
    raise InputError(
        f"unknown scheduler {spec!r}; valid: {SCHEDULER_HELP} (N a positive integer)",
        field="scheduler",
    )
