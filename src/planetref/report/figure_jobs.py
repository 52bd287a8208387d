"""Figures drawn in a child process while the run goes on.

Matplotlib's layout and PNG encoding cost a few CPU seconds per figure whatever the strip
length, all in one Python thread. :class:`FigureJobs` draws them in one child process
(started with ``spawn``, so nothing of the parent's threads or locks is inherited), in
the order they are submitted, while the parent adjusts and writes the other outputs; the
parent waits for them (:meth:`FigureJobs.wait`) before it writes its report. A figure
never sinks a run: its error becomes a warning. Without a child process
(``background=False``, or when none can be started) the figures are drawn at submission.

The functions and their arguments travel by pickle: module-level functions and plain
data (numpy arrays, dataclasses of them), not open rasters or cameras.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

__all__ = ["FigureJobs"]

log = logging.getLogger("planetref.report")


class FigureJobs:
    """Figures drawn one after another in a child process (see the module doc).

    Args:
        background: Draw in a child process (else at submission, in this process).
    """

    def __init__(self, background: bool = True) -> None:
        self.background = background
        self._pool: Any = None
        self._pending: list[tuple[str, Future[Any]]] = []

    def __enter__(self) -> FigureJobs:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _executor(self) -> Any:
        if self._pool is None and self.background:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            try:
                self._pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
            except (OSError, ValueError) as exc:  # pragma: no cover - no processes here
                log.info("figures drawn in this process (no child process: %s)", exc)
                self.background = False
        return self._pool

    def submit(self, label: str, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        """Draw a figure: ``fn(*args, **kwargs)`` (``label`` names it in a warning)."""
        pool = self._executor()
        if pool is not None:
            try:
                self._pending.append((label, pool.submit(fn, *args, **kwargs)))
                return
            except RuntimeError as exc:  # pragma: no cover - a broken pool
                log.info("figure %s drawn in this process (%s)", label, exc)
        try:
            fn(*args, **kwargs)
        except Exception as exc:  # a figure never sinks a run
            log.warning("no figure %s: %s", label, exc)

    def wait(self) -> None:
        """Wait for every submitted figure; each error is logged as a warning."""
        pending, self._pending = self._pending, []
        for label, fut in pending:
            try:
                fut.result()
            except Exception as exc:  # a figure never sinks a run
                log.warning("no figure %s: %s", label, exc)

    def close(self) -> None:
        """Wait for the figures and end the child process."""
        try:
            self.wait()
        finally:
            if self._pool is not None:
                self._pool.shutdown(wait=True)
                self._pool = None
