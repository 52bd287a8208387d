"""Figures drawn in a child process while the run goes on.

Matplotlib's layout and PNG encoding cost a few CPU seconds per figure whatever the strip
length, all in one Python thread. :class:`FigureJobs` draws them in one child process
(``python -m planetref.report.figure_worker``: a fresh interpreter, so nothing of the
parent's threads or locks is inherited, and, unlike ``multiprocessing``'s ``spawn``, the
caller's ``__main__`` script is never run again), in the order they are submitted, while
the parent adjusts and writes the other outputs; the parent waits for them
(:meth:`FigureJobs.wait`) before it writes its report. A figure never sinks a run: its
error becomes a warning. Without a child process (``background=False``, or when none can
be started) the figures are drawn at submission.

Each task is pickled into a temporary file (so that submitting never waits for the
child) and only its path goes down the pipe: functions must be module-level and the
arguments plain data (numpy arrays, dataclasses of them), not open rasters or cameras.
"""

from __future__ import annotations

import logging
import os
import pickle
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["FigureJobs"]

log = logging.getLogger("planetref.report")


def _child_env() -> dict[str, str]:
    """The environment of the child: this one, with planetref's folder on PYTHONPATH.

    An installed planetref (in a site-packages folder) is found anyway; a source checkout
    that this process imports through ``sys.path`` is put on the child's PYTHONPATH.
    """
    import site

    env = dict(os.environ)
    here = Path(__file__).resolve().parents[2]  # the folder holding planetref/
    sites = {Path(p).resolve() for p in [*site.getsitepackages(), site.getusersitepackages()]}
    if here not in sites:
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(here), env.get("PYTHONPATH", "")) if p)
    return env


class FigureJobs:
    """Figures drawn one after another in a child process (see the module doc).

    Args:
        background: Draw in a child process (else at submission, in this process).
    """

    def __init__(self, background: bool = True) -> None:
        self.background = background
        self._proc: subprocess.Popen[str] | None = None
        self._tmp: tempfile.TemporaryDirectory[str] | None = None
        self._pending: list[str] = []
        self._n = 0

    def __enter__(self) -> FigureJobs:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _child(self) -> subprocess.Popen[str] | None:
        if self._proc is None and self.background:
            try:
                self._tmp = tempfile.TemporaryDirectory(prefix="planetref-figures-")
                self._proc = subprocess.Popen(
                    [sys.executable, "-m", "planetref.report.figure_worker"],
                    stdin=subprocess.PIPE,
                    stdout=subprocess.PIPE,
                    text=True,
                    env=_child_env(),
                )
            except OSError as exc:  # pragma: no cover - no processes here
                log.info("figures drawn in this process (no child process: %s)", exc)
                self.background = False
        return self._proc

    def start(self) -> None:
        """Start the child process now (it imports matplotlib while the caller works on).

        Otherwise it starts with the first figure.
        """
        self._child()

    def submit(self, label: str, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        """Draw a figure: ``fn(*args, **kwargs)`` (``label`` names it in a warning)."""
        proc = self._child()
        if proc is not None and proc.stdin is not None and self._tmp is not None:
            self._n += 1
            task = Path(self._tmp.name) / f"task{self._n:04d}.pickle"
            try:
                with task.open("wb") as fh:
                    pickle.dump((fn, args, kwargs), fh, protocol=pickle.HIGHEST_PROTOCOL)
                proc.stdin.write(f"{task}\n")
                proc.stdin.flush()
                self._pending.append(label)
                return
            except (OSError, pickle.PicklingError, AttributeError, TypeError) as exc:
                log.info("figure %s drawn in this process (%s)", label, exc)
        try:
            fn(*args, **kwargs)
        except Exception as exc:  # a figure never sinks a run
            log.warning("no figure %s: %s", label, exc)

    def wait(self) -> None:
        """Wait for every submitted figure; each error is logged as a warning."""
        pending, self._pending = self._pending, []
        out = None if self._proc is None else self._proc.stdout
        for label in pending:
            reply = "" if out is None else out.readline().strip()
            if reply != "ok":
                why = reply.removeprefix("error ") or "the figure process ended"
                log.warning("no figure %s: %s", label, why)

    def close(self) -> None:
        """Wait for the figures and end the child process."""
        try:
            self.wait()
        finally:
            if self._proc is not None:
                if self._proc.stdin is not None:
                    self._proc.stdin.close()
                self._proc.wait()
                if self._proc.stdout is not None:
                    self._proc.stdout.close()
                self._proc = None
            if self._tmp is not None:
                self._tmp.cleanup()
                self._tmp = None
