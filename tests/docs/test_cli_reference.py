"""Every command and option is in the generated CLI reference; quoted commands parse."""

from __future__ import annotations

import itertools
import re
import shlex
from pathlib import Path

import cli_ref
import click
import pytest
from click.testing import CliRunner

from planetref.cli import main

ROOT = Path(__file__).resolve().parents[2]


def _walk(group: click.Command, path: tuple[str, ...]):
    yield path, group
    if isinstance(group, click.Group):
        ctx = click.Context(group)
        for name in group.list_commands(ctx):
            yield from _walk(group.get_command(ctx, name), (*path, name))


COMMANDS = dict(_walk(main, ("planetref",)))
PAGE = cli_ref.page()


def test_every_command_and_option_is_in_the_reference():
    assert len(COMMANDS) >= 15  # groups and their sub-commands were found
    sections = re.split(r"^#+ `(planetref[^`]*)`$", PAGE, flags=re.M)
    by_name = dict(zip(sections[1::2], sections[2::2], strict=True))
    for path, cmd in COMMANDS.items():
        name = " ".join(path)
        assert name in by_name, f"{name} missing from the CLI reference"
        for param in cmd.params:
            for opt in getattr(param, "opts", []):
                if opt.startswith("-"):
                    assert f"`{opt}`" in by_name[name], f"{name} {opt} missing"


def _quoted_commands() -> list[tuple[str, str]]:
    """(file, line) of every ``planetref ...`` command in a code block of the docs."""
    files = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    out = []
    for f in files:
        in_code = False
        # continuation lines (a trailing backslash) belong to the command
        text = f.read_text(encoding="utf-8").replace("\\\n", " ")
        for line in text.splitlines():
            if line.lstrip().startswith("```"):
                in_code = not in_code
                continue
            stripped = line.strip()
            if in_code and stripped.startswith("planetref "):
                out.append((str(f.relative_to(ROOT)), stripped))
    return out


QUOTED = _quoted_commands()


def _resolve(words: list[str]) -> tuple[tuple[str, ...], click.Command, list[str]]:
    """The deepest command the words name, and the words after it."""
    path: tuple[str, ...] = ("planetref",)
    cmd: click.Command = main
    rest = list(words)
    while rest and isinstance(cmd, click.Group) and not rest[0].startswith("-"):
        sub = cmd.get_command(click.Context(cmd), rest[0])
        if sub is None:
            break
        path, cmd, rest = (*path, rest[0]), sub, rest[1:]
    return path, cmd, rest


def test_quoted_commands_were_found():
    assert len(QUOTED) >= 20
    assert any(f == "README.md" for f, _ in QUOTED)


@pytest.mark.parametrize(("source", "line"), QUOTED, ids=[f"{f}:{c[:50]}" for f, c in QUOTED])
def test_quoted_command_names_a_command_and_its_options(source, line):
    code = line.split("#", 1)[0]
    code = code.replace("[", " ").replace("]", " ").replace("|", " ")
    words = shlex.split(code)[1:]
    global_opts = {"-v", "-q", "-vv", "--verbose", "--quiet"}
    words = [w for w in words if w not in global_opts]
    path, cmd, rest = _resolve(words)
    assert not isinstance(cmd, click.Group) or not rest or rest[0].startswith("-"), (
        f"{source}: unknown command in {line!r}"
    )
    known = {o for p in cmd.params for o in (*p.opts, *getattr(p, "secondary_opts", []))}
    for word in rest:
        opt = word.split("=", 1)[0]
        if re.fullmatch(r"--[a-z][a-z0-9-]*", opt):
            assert opt in known, f"{source}: {' '.join(path)} has no option {opt} ({line!r})"
    result = CliRunner().invoke(main, [*path[1:], "--help"])
    assert result.exit_code == 0, result.output


def test_readme_links_point_at_files():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", text):
        if "://" in target:
            continue
        assert (ROOT / target).exists(), f"README links to a missing file: {target}"


def _documented_outputs() -> list[tuple[str, str, str]]:
    """(file, command, printed output) where a quoted command is followed by ``# {...}``."""
    out = []
    for f in [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]:
        lines = f.read_text(encoding="utf-8").splitlines()
        for line, nxt in itertools.pairwise(lines):
            cmd, expected = line.strip(), nxt.strip()
            if cmd.startswith("planetref camera ") and expected.startswith("# {"):
                out.append((str(f.relative_to(ROOT)), cmd, expected[2:]))
    return out


DOCUMENTED = _documented_outputs()


def test_documented_outputs_were_found():
    assert len(DOCUMENTED) >= 2


@pytest.mark.shared
@pytest.mark.parametrize(("source", "command", "expected"), DOCUMENTED)
def test_documented_command_prints_what_the_docs_say(source, command, expected, monkeypatch):
    """The camera commands the tutorials quote, run on ../shared, print the quoted numbers."""
    import json

    args = shlex.split(command)[1:]
    files = [a for a in args if a.startswith("../shared/")]
    if not all((ROOT / a).exists() for a in files):
        pytest.skip("../shared data not found")
    monkeypatch.chdir(ROOT)
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    actual = json.loads(result.output)
    for key, value in json.loads(expected).items():
        # as many decimals as the docs print
        decimals = len(str(value).split(".")[1]) if "." in str(value) else 0
        assert actual[key] == pytest.approx(value, abs=0.6 * 10.0**-decimals), (source, key)
