"""The command-line reference, generated from planetref's click group.

Walks :data:`planetref.cli.main` (the ``planetref`` command) and every sub-command and
sub-group it lists; for each, the usage line, the help text and a table of its options
and arguments, as click itself defines them. Nothing here is typed by hand.
"""

from __future__ import annotations

from collections.abc import Iterator

import click


def commands(
    group: click.Command | None = None, path: tuple[str, ...] = ("planetref",)
) -> Iterator[tuple[tuple[str, ...], click.Command]]:
    """``(path, command)`` for the ``planetref`` command and every command below it."""
    if group is None:
        from planetref.cli import main

        group = main
    yield path, group
    if isinstance(group, click.Group):
        ctx = click.Context(group, info_name=path[-1])
        for name in group.list_commands(ctx):
            sub = group.get_command(ctx, name)
            if sub is not None and not sub.hidden:
                yield from commands(sub, (*path, name))


def _context(path: tuple[str, ...], command: click.Command) -> click.Context:
    parent = None
    for name in path[:-1]:
        parent = click.Context(click.Command(name), info_name=name, parent=parent)
    return click.Context(command, info_name=path[-1], parent=parent)


def _cell(text: str) -> str:
    return " ".join(text.replace("|", "\\|").split())


def _default_text(param: click.Parameter) -> str:
    """The default shown for a parameter ('' where there is none worth showing)."""
    default = param.default
    if (
        default is None
        or default is False
        or callable(default)
        or type(default).__name__ == "Sentinel"  # click >= 8.3: "no default"
        or getattr(param, "show_default", None) is False
    ):
        return ""
    if isinstance(default, (list, tuple)):
        return " ".join(map(str, default))
    return str(default)


def _param_row(param: click.Parameter, ctx: click.Context) -> str:
    metavar = param.make_metavar(ctx) if _takes_ctx() else param.make_metavar()  # type: ignore[call-arg]
    if isinstance(param, click.Option):
        names = ", ".join(f"`{n}`" for n in (*param.opts, *param.secondary_opts))
        kind = "count" if param.count else ("flag" if param.is_flag else metavar)
        help_text = param.help or ""
        if param.multiple:
            help_text += " (repeatable)"
        if param.required:
            help_text += " (required)"
    else:
        names = f"`{metavar}`"
        kind = "argument"
        help_text = "required" if param.required else "optional"
        if getattr(param, "nargs", 1) == -1:
            help_text += ", any number"
    default = _default_text(param)
    shown = f"`{_cell(default)}`" if default else ""
    return f"| {names} | {_cell(str(kind))} | {shown} | {_cell(help_text)} |"


def _takes_ctx() -> bool:
    """Whether this click's ``make_metavar`` takes the context (click >= 8.2)."""
    import inspect

    return "ctx" in inspect.signature(click.Parameter.make_metavar).parameters


def section(path: tuple[str, ...], command: click.Command) -> str:
    """The Markdown section of one command: heading, usage, help and parameters."""
    ctx = _context(path, command)
    name = " ".join(path)
    depth = min(len(path) + 1, 4)
    usage = " ".join(command.collect_usage_pieces(ctx))
    out = [f"{'#' * depth} `{name}`\n", f"```\n{name} {usage}\n```\n"]
    if command.help:
        out.append(_help_markdown(command.help) + "\n")
    rows = [p for p in command.get_params(ctx) if not getattr(p, "hidden", False)]
    if rows:
        out.append("| option | value | default | description |")
        out.append("|---|---|---|---|")
        out.extend(_param_row(p, ctx) for p in rows)
        out.append("")
    if isinstance(command, click.Group):
        subs = command.list_commands(ctx)
        if subs:
            out.append("Commands: " + ", ".join(f"`{name} {s}`" for s in subs) + ".\n")
    return "\n".join(out)


def _help_markdown(text: str) -> str:
    """Turn click help text (a backspace line marks a verbatim paragraph) into Markdown."""
    import inspect

    paragraphs = inspect.cleandoc(text).split("\n\n")
    out = []
    for para in paragraphs:
        if para.startswith("\b"):
            body = para[1:].strip("\n")
            out.append("```\n" + body + "\n```")
        else:
            out.append(" ".join(para.split()))
    return "\n\n".join(out)


def page() -> str:
    """The whole command-line reference page (Markdown)."""
    parts = [
        "# Command-line reference\n",
        "*Generated from the click commands by `docs/gen/cli_ref.py` at every build; "
        "do not edit.* `planetref COMMAND --help` prints the same.\n",
        "Every error is one line on stderr naming the file and the problem (exit status "
        "1); `-vv` adds the traceback.\n",
    ]
    parts.extend(section(path, cmd) for path, cmd in commands())
    return "\n".join(parts)


if __name__ == "__main__":
    print(page())
