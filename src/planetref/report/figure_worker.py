"""The child process of :class:`~planetref.report.figure_jobs.FigureJobs`.

Run as ``python -m planetref.report.figure_worker``. It reads task file paths from stdin,
one per line; each file holds a pickled ``(function, args, kwargs)``, which it runs (and
then removes the file). For every task it writes one line to its reply channel (the
original stdout): ``ok`` or ``error <message>``. Anything the figures print goes to
stderr, so it cannot garble the replies. The process ends when stdin closes.
"""

from __future__ import annotations

import os
import pickle
import sys
from pathlib import Path


def main() -> int:
    """Run the tasks named on stdin until it closes."""
    replies = os.fdopen(os.dup(1), "w", encoding="utf-8")
    os.dup2(2, 1)  # stray prints go to stderr, not into the replies
    for line in sys.stdin:
        path = Path(line.strip())
        if not line.strip():
            continue
        try:
            with path.open("rb") as fh:
                fn, args, kwargs = pickle.load(fh)
            fn(*args, **kwargs)
            reply = "ok"
        except Exception as exc:  # reported to the parent, which logs a warning
            reply = "error " + f"{type(exc).__name__}: {exc}".replace("\n", " ")
        finally:
            path.unlink(missing_ok=True)
        replies.write(reply + "\n")
        replies.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
