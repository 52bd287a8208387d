"""Expected conditions are notes: INFO in the log, one summary line on the terminal."""

import logging

import click
import pytest

from planetref.cli import _summarize_notes, main
from planetref.runtime.notes import NoteCounter, log_note


@pytest.fixture
def planetref_at_info():
    logger = logging.getLogger("planetref")
    level = logger.level
    logger.setLevel(logging.INFO)  # as inside a run (its log file takes INFO)
    yield logger
    logger.setLevel(level)


def test_counter_counts_notes_only(planetref_at_info):
    counter = NoteCounter()
    planetref_at_info.addHandler(counter)
    try:
        log = logging.getLogger("planetref.adjust")
        for _ in range(3):
            log_note(log, "camera footprints moved", "1 camera footprint(s) moved ...")
        log_note(log, "node attitude correlations", "6 parameter pair(s) correlate ...")
        log.warning("an actionable warning")
        log.info("plain information")
    finally:
        planetref_at_info.removeHandler(counter)
    assert dict(counter.counts) == {"camera footprints moved": 3, "node attitude correlations": 1}
    line = counter.summary()
    assert "\n" not in line and line.startswith("note: 4 expected condition(s)")
    assert "camera footprints moved x3, node attitude correlations x1" in line
    assert NoteCounter().summary() is None


@pytest.mark.parametrize(("verbosity", "printed"), [(0, True), (1, False), (-1, False)])
def test_one_summary_line_at_the_end_of_a_command(planetref_at_info, capsys, verbosity, printed):
    with click.Context(main):
        ctx = click.get_current_context()
        _summarize_notes(ctx, verbosity)
        log_note(logging.getLogger("planetref.adjust"), "camera footprints moved", "moved")
        log_note(logging.getLogger("planetref.adjust"), "camera footprints moved", "moved")
        assert capsys.readouterr().err == ""  # nothing before the command ends
    err = capsys.readouterr().err
    assert (err.count("\n") == 1 and "2 expected condition(s)" in err) == printed
    assert not printed or err.startswith("note: ")


def test_library_deprecation_warnings_are_notes(planetref_at_info, caplog):
    from planetref.cli import _warning_as_log_line

    counter = NoteCounter()
    planetref_at_info.addHandler(counter)
    try:
        with caplog.at_level(logging.INFO, logger="planetref"):
            _warning_as_log_line(
                PendingDeprecationWarning("Use `@` matmul instead of `*`"),
                PendingDeprecationWarning,
                "x.py",
                1,
            )
            _warning_as_log_line(RuntimeWarning("overflow"), RuntimeWarning, "x.py", 1)
    finally:
        planetref_at_info.removeHandler(counter)
    levels = {r.getMessage(): r.levelno for r in caplog.records}
    assert levels == {
        "PendingDeprecationWarning: Use `@` matmul instead of `*`": logging.INFO,
        "RuntimeWarning: overflow": logging.WARNING,
    }
    assert dict(counter.counts) == {"library deprecation warnings": 1}
