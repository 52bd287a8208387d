"""The ``planetref`` command line.

Sub-commands are registered explicitly in :data:`COMMANDS` and imported only when they
run, so ``planetref camera ...`` does not pay for importing torch. Every
:class:`~planetref.errors.PlanetrefError` ends the command with a one-line message and
exit status 1; no traceback is shown unless ``-vv`` is given.
"""

from __future__ import annotations

import importlib
import logging
import sys
import warnings
from typing import Any

import click

from planetref import __version__
from planetref.errors import PlanetrefError

__all__ = ["COMMANDS", "main"]

# name -> "module:attribute" of a click command; explicit, no plugin discovery.
COMMANDS: dict[str, str] = {
    "info": "planetref.cli.info:info_command",
    "camera": "planetref.cli.camera:camera_group",
    "matchers": "planetref.cli.match:matchers_command",
    "match": "planetref.cli.match:match_command",
    "simulate": "planetref.cli.simulate:simulate_command",
    "adjust": "planetref.cli.adjust:adjust_command",
    "georef": "planetref.cli.georef:georef_command",
    "compare": "planetref.cli.georef:compare_command",
    "demo": "planetref.cli.georef:demo_command",
    "scene": "planetref.cli.scene:scene_group",
    "weights": "planetref.cli.weights:weights_group",
}

log = logging.getLogger("planetref")


def _one_line(message: str) -> str:
    """A message on one line (the CLI's errors are exactly one line on stderr)."""
    return "; ".join(part.strip() for part in message.splitlines() if part.strip())


class _LazyGroup(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(name for name in COMMANDS if self._available(name))

    @staticmethod
    def _available(name: str) -> bool:
        module = COMMANDS[name].split(":")[0]
        return importlib.util.find_spec(module) is not None

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        target = COMMANDS.get(cmd_name)
        if target is None or not self._available(cmd_name):
            return None
        module, attr = target.split(":")
        cmd = getattr(importlib.import_module(module), attr)
        cmd.name = cmd_name
        return cmd

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except PlanetrefError as exc:
            if ctx.obj and ctx.obj.get("verbosity", 0) >= 2:
                raise
            raise click.ClickException(_one_line(str(exc))) from None
        except (
            click.ClickException,
            click.exceptions.Exit,
            click.exceptions.Abort,
            KeyboardInterrupt,
        ):
            raise
        except (OSError, MemoryError) as exc:
            if ctx.obj and ctx.obj.get("verbosity", 0) >= 2:
                raise
            raise click.ClickException(_one_line(f"{type(exc).__name__}: {exc}")) from None
        except Exception as exc:
            # A bug, not bad input: one line here, the traceback with -vv.
            if ctx.obj and ctx.obj.get("verbosity", 0) >= 2:
                raise
            raise click.ClickException(
                _one_line(
                    f"internal error ({type(exc).__name__}: {exc}); rerun with -vv for the "
                    "traceback and please report it"
                )
            ) from None


def _configure_logging(verbosity: int) -> None:
    level = {-1: logging.ERROR, 0: logging.WARNING, 1: logging.INFO}.get(
        max(-1, min(verbosity, 2)), logging.DEBUG
    )
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger("planetref")
    root.handlers[:] = [handler]
    root.setLevel(level)


def _warning_as_log_line(
    message: Warning | str,
    category: type[Warning],
    filename: str,
    lineno: int,
    file: Any = None,
    line: str | None = None,
) -> None:
    """Show a Python warning as one log line (no source path or code line).

    rasterio's ``NotGeoreferencedWarning`` is dropped: raw CCD images and the images of
    ``match`` have no georeference by nature. Deprecation warnings (of the libraries
    planetref calls) are notes (:mod:`planetref.runtime.notes`): INFO, and counted.
    """
    if category.__name__ == "NotGeoreferencedWarning":
        return
    text = _one_line(str(message))
    if not issubclass(category, UserWarning) or category.__module__ != "builtins":
        text = f"{category.__name__}: {text}"
    logger = logging.getLogger("planetref.warnings")
    if issubclass(category, (DeprecationWarning, PendingDeprecationWarning)):
        # A library's deprecation asks the developers, not the user, to act: a note.
        from planetref.runtime.notes import log_note

        log_note(logger, "library deprecation warnings", text)
        return
    logger.warning("%s", text)


def _route_warnings(ctx: click.Context) -> None:
    """Show warnings as one ``WARNING`` line while the command runs.

    Like every other message they go to stderr (and to the run's log); the previous
    handler is restored when the command ends.
    """
    previous = warnings.showwarning
    warnings.showwarning = _warning_as_log_line

    def restore() -> None:
        warnings.showwarning = previous

    ctx.call_on_close(restore)


def _summarize_notes(ctx: click.Context, verbosity: int) -> None:
    """Count the notes the command logs; at the end, one line about them on stderr.

    Notes are expected conditions logged at INFO (:mod:`planetref.runtime.notes`): the
    run's log has each; at the default verbosity the terminal gets this one line
    instead (``-v`` prints them, ``-q`` neither).
    """
    from planetref.runtime.notes import NoteCounter

    counter = NoteCounter()
    logger = logging.getLogger("planetref")
    logger.addHandler(counter)

    def close() -> None:
        logger.removeHandler(counter)
        line = counter.summary()
        if line and verbosity == 0:
            click.echo(line, err=True)

    ctx.call_on_close(close)


@click.group(cls=_LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, "--version", prog_name="planetref")
@click.option("-v", "--verbose", count=True, help="More output (-vv: debug, with tracebacks).")
@click.option("-q", "--quiet", count=True, help="Less output (errors only, no progress bars).")
@click.pass_context
def main(ctx: click.Context, verbose: int, quiet: int) -> None:
    """planetref: georeference planetary push-broom images without ground control points."""
    ctx.ensure_object(dict)
    ctx.obj["verbosity"] = verbose - quiet
    ctx.obj["quiet"] = quiet > 0
    _configure_logging(verbose - quiet)
    _route_warnings(ctx)
    _summarize_notes(ctx, verbose - quiet)
