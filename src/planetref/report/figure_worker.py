"""The child process of :class:`~planetref.report.figure_jobs.FigureJobs`.

Run as ``python -m planetref.report.figure_worker``. It reads task file paths from stdin,
one per line; each file holds a pickled ``(function, args, kwargs)``, which it runs (and
then removes the file). For every task it writes one line to its reply channel (the
original stdout): ``ok`` or ``error <message>``. Anything the figures print goes to
stderr, so it cannot garble the replies. The process ends when stdin closes.

Before it reads its first task it imports matplotlib and the figure modules
(:func:`warm`), so a process started early (:meth:`FigureJobs.start
<planetref.report.figure_jobs.FigureJobs.start>`) has them ready when the figures come.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import sys
from pathlib import Path


def warm() -> None:
    """Import what the figures need: matplotlib's canvas, the figure modules, a KD-tree."""
    import matplotlib.backends.backend_agg
    import matplotlib.figure  # noqa: F401
    import scipy.spatial  # noqa: F401

    import planetref.report.figures_adjust
    import planetref.report.figures_matching  # noqa: F401


def main() -> int:
    """Run the tasks named on stdin until it closes.

    The worker belongs to the run that started it
    (:func:`planetref.runtime.execute.bind_to_parent`): Ctrl-C reaches the whole terminal
    process group, and the worker ignores SIGINT (the parent stops, closes stdin, and the
    worker ends after its task), so an interrupted run prints no KeyboardInterrupt
    traceback from here; a parent that dies outright ends the worker within half a
    second, and no task queued before is started after it is gone.
    """
    from planetref.runtime.execute import bind_to_parent

    parent = os.getppid()
    bind_to_parent(parent, death_signal=False)
    replies = os.fdopen(os.dup(1), "w", encoding="utf-8")
    os.dup2(2, 1)  # stray prints go to stderr, not into the replies
    try:
        warm()
    except ImportError:
        pass  # each figure then says what it lacks
    for line in sys.stdin:
        path = Path(line.strip())
        if not line.strip():
            continue
        if os.getppid() != parent:
            return 0  # the run is gone: its figures are not drawn
        try:
            with path.open("rb") as fh:
                fn, args, kwargs = pickle.load(fh)
            fn(*args, **kwargs)
            reply = "ok"
        except Exception as exc:  # reported to the parent, which logs a warning
            reply = "error " + f"{type(exc).__name__}: {exc}".replace("\n", " ")
        finally:
            path.unlink(missing_ok=True)
        try:
            replies.write(reply + "\n")
            replies.flush()
        except BrokenPipeError:  # the parent stopped listening (interrupted, killed)
            # The buffered reply is flushed again at exit: into /dev/null, quietly.
            with contextlib.suppress(OSError):
                os.dup2(os.open(os.devnull, os.O_WRONLY), replies.fileno())
            return 0
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
