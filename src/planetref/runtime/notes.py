"""Notes: log records about expected conditions, counted into one summary line.

A run meets conditions worth recording that ask nothing of the user (a camera footprint
moved by the hundred metres the initial cameras were off; attitude angles of
neighbouring orientation nodes correlate as interpolation couples them). They are logged
at INFO, so the run's ``planetref.log`` keeps every one, and tagged with a short kind;
:class:`NoteCounter` counts them so that the command line prints one line about them
instead of one ``WARNING`` each. What the user must act on stays a ``WARNING``.
"""

from __future__ import annotations

import logging
from collections import Counter

__all__ = ["NOTE_ATTR", "NoteCounter", "log_note"]

NOTE_ATTR = "planetref_note"
"""The log record attribute that holds a note's kind."""


def log_note(logger: logging.Logger, kind: str, message: str) -> None:
    """Log ``message`` at INFO as a note of ``kind`` (a short plural noun phrase)."""
    logger.info("%s", message, extra={NOTE_ATTR: kind})


class NoteCounter(logging.Handler):
    """Counts the notes logged while it is attached, per kind (it writes nothing)."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.counts: Counter[str] = Counter()

    def emit(self, record: logging.LogRecord) -> None:
        """Count ``record`` when it is a note."""
        kind = getattr(record, NOTE_ATTR, None)
        if kind:
            self.counts[str(kind)] += 1

    def summary(self) -> str | None:
        """One line naming how many notes of each kind were logged, or None."""
        if not self.counts:
            return None
        total = sum(self.counts.values())
        kinds = ", ".join(f"{kind} x{n}" for kind, n in self.counts.most_common())
        return (
            f"note: {total} expected condition(s) logged at INFO ({kinds}); each run's "
            "planetref.log and report list them, -v prints them"
        )
