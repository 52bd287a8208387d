"""The benchmarks page, generated from the benchmark scripts' JSON results.

Every file ``benchmarks/results/*.json`` is one result of one benchmark script, written by
the script itself (``--json-out``; :func:`benchmarks.machine.write_result`): the figures
it measured, the machine, the date and the command. The page shows the latest result of
each benchmark; nothing on it is typed by hand. The schema is deliberately loose so that
older scripts' JSON still shows:

* ``benchmark`` (default: the file name), ``title``, ``description`` (default: the first
  paragraph of the script's docstring);
* ``date`` (ISO 8601), ``command`` (the command line), ``machine``
  (:func:`benchmarks.machine.describe`);
* ``figures``: a list of ``{"name", "value", "unit", "note"}``, or a mapping of name to
  value (or to such a record); without ``figures`` every other top-level key is a figure.
"""

from __future__ import annotations

import ast
import json
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "benchmarks" / "results"
META_KEYS = {"benchmark", "title", "description", "date", "command", "machine", "figures"}
#: Keys of a result that hold raw measurements behind its figures: in the JSON file only.
DETAIL_KEYS = {"sizes", "tiles", "details"}


@dataclass(frozen=True)
class Figure:
    """One measured figure of a benchmark result."""

    name: str
    value: object
    unit: str = ""
    note: str = ""


@dataclass(frozen=True)
class Result:
    """One benchmark result file, normalised."""

    benchmark: str
    title: str
    description: str
    date: str
    command: str
    machine: dict[str, object]
    figures: tuple[Figure, ...]
    source: str


def _flatten(prefix: str, value: object) -> list[Figure]:
    if isinstance(value, dict) and not ({"value"} <= set(value)):
        out: list[Figure] = []
        for k, v in value.items():
            out.extend(_flatten(f"{prefix}.{k}" if prefix else str(k), v))
        return out
    if isinstance(value, dict):
        return [
            Figure(
                str(value.get("name", prefix)),
                value["value"],
                str(value.get("unit", "")),
                str(value.get("note", "")),
            )
        ]
    return [Figure(prefix, value)]


def _script_summary(benchmark: str) -> str:
    """The first paragraph of ``benchmarks/<benchmark>.py``'s docstring ('' if none)."""
    script = ROOT / "benchmarks" / f"{benchmark}.py"
    if not script.is_file():
        return ""
    doc = ast.get_docstring(ast.parse(script.read_text(encoding="utf-8"))) or ""
    return " ".join(doc.split("\n\n")[0].split())


def load(path: Path) -> Result:
    """One result file as a :class:`Result` (raises ``ValueError`` naming the file)."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a readable JSON benchmark result ({exc})") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: a benchmark result must be a JSON object")
    benchmark = str(doc.get("benchmark") or path.stem)
    raw = doc.get("figures")
    if raw is None:
        raw = {k: v for k, v in doc.items() if k not in META_KEYS | DETAIL_KEYS}
    figures: list[Figure] = []
    if isinstance(raw, list):
        for item in raw:
            if isinstance(item, dict) and "name" in item:
                figures.extend(_flatten(str(item["name"]), item))
    else:
        figures = _flatten("", raw)
    machine = doc.get("machine") if isinstance(doc.get("machine"), dict) else {}
    return Result(
        benchmark=benchmark,
        title=str(doc.get("title") or benchmark),
        description=str(doc.get("description") or _script_summary(benchmark)),
        date=str(doc.get("date") or ""),
        command=str(doc.get("command") or ""),
        machine=machine,
        figures=tuple(figures),
        source=path.name,
    )


def latest(results_dir: Path = RESULTS) -> list[Result]:
    """The latest result of each benchmark (by ``date``), sorted by benchmark name."""
    best: dict[str, Result] = {}
    for path in sorted(results_dir.glob("*.json")):
        r = load(path)
        if r.benchmark not in best or r.date > best[r.benchmark].date:
            best[r.benchmark] = r
    return [best[k] for k in sorted(best)]


def _cell(value: object) -> str:
    if isinstance(value, float):
        text = f"{value:.4g}"
    elif isinstance(value, (list, tuple)) and (
        len(value) > 8 or any(isinstance(v, dict | list | tuple) for v in value)
    ):
        text = f"{len(value)} entries (see the JSON file)"
    elif isinstance(value, (list, tuple)):
        text = ", ".join(_cell(v) for v in value)
    elif value is None:
        text = "-"
    else:
        text = str(value)
    return " ".join(text.replace("|", "\\|").split())


def _machine_text(machine: dict[str, object]) -> str:
    if not machine:
        return "not recorded"
    parts = [str(machine.get("cpu") or "unknown CPU")]
    if machine.get("cpu_family") is not None:
        parts.append(f"family {machine['cpu_family']} model {machine.get('cpu_model')}")
    if machine.get("cores") is not None:
        parts.append(f"{machine['cores']} cores available")
    if machine.get("load_1min") is not None:
        parts.append(f"load {machine['load_1min']} at the start")
    extra = {
        k: v
        for k, v in machine.items()
        if k not in {"cpu", "cpu_family", "cpu_model", "cores", "load_1min"}
    }
    parts.extend(f"{k} {_cell(v)}" for k, v in extra.items())
    return ", ".join(parts)


def section(result: Result) -> str:
    """The Markdown section of one result."""
    out = [f"## {result.title}\n"]
    if result.description:
        out.append(result.description + "\n")
    out.append(f"- **Date**: {result.date or 'not recorded'}")
    out.append(f"- **Machine**: {_machine_text(result.machine)}")
    out.append(f"- **Command**: `{result.command}`" if result.command else "- **Command**: -")
    out.append(f"- **File**: `benchmarks/results/{result.source}`\n")
    if result.figures:
        out.append("| figure | value | unit | note |")
        out.append("|---|--:|---|---|")
        out.extend(
            f"| {_cell(f.name)} | {_cell(f.value)} | {_cell(f.unit)} | {_cell(f.note)} |"
            for f in result.figures
        )
        out.append("")
    return "\n".join(out)


def page(results_dir: Path = RESULTS) -> str:
    """The whole benchmarks page (Markdown)."""
    results = latest(results_dir)
    head = (
        "# Benchmarks\n\n"
        "*Generated by `docs/gen/benchmarks_page.py` from the JSON results in "
        "`benchmarks/results/` at every build; do not edit.*\n\n"
        "Each benchmark script under `benchmarks/` prints its figures and, with "
        "`--json-out FILE`, writes them with the machine, date and command. "
        "The latest result of each benchmark is shown. Timings are CPU seconds or ratios "
        "measured in the same run where the script can give them: wall-clock seconds "
        "depend on what else the machine was doing (its load at the start is recorded). "
        "To add or refresh a result, run the command shown with "
        "`--json-out benchmarks/results/NAME.json` and rebuild the docs.\n\n"
    )
    if not results:
        return head + "No results yet.\n"
    index = "\n".join(f"- [{r.title}](#{_anchor(r.title)})" for r in results)
    return head + index + "\n\n" + "\n".join(section(r) for r in results)


def _anchor(title: str) -> str:
    """The anchor Python-Markdown's toc extension gives a heading (its default slugify)."""
    import re
    import unicodedata

    text = unicodedata.normalize("NFKD", title).encode("ascii", "ignore").decode("ascii")
    text = re.sub(r"[^\w\s-]", "", text).strip().lower()
    return re.sub(r"[-\s]+", "-", text)


if __name__ == "__main__":
    print(page())
