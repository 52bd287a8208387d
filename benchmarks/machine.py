"""The machine a benchmark ran on, for its printed figures (timings name the machine).

Imported by the benchmark scripts (their folder is first on ``sys.path`` when they run as
scripts). Linux: the CPU model, family and model numbers from ``/proc/cpuinfo``.
"""

from __future__ import annotations

import os
import platform


def describe() -> dict[str, object]:
    """``{"cpu", "cpu_family", "cpu_model", "cores", "load_1min"}`` of this machine.

    ``cores`` is the CPUs this process may use; ``load_1min`` the load average when the
    benchmark starts (other jobs on the cores inflate wall-clock figures).
    """
    fields: dict[str, str] = {}
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                key, _, value = line.partition(":")
                key = key.strip()
                if not key and fields:
                    break  # the first processor's block is enough
                fields.setdefault(key, value.strip())
    except OSError:
        pass
    try:
        cores = len(os.sched_getaffinity(0))
        load = round(os.getloadavg()[0], 2)
    except (AttributeError, OSError):
        cores, load = os.cpu_count() or 0, None
    return {
        "cpu": fields.get("model name") or platform.processor() or platform.machine(),
        "cpu_family": fields.get("cpu family"),
        "cpu_model": fields.get("model"),
        "cores": cores,
        "load_1min": load,
    }


def result_record(
    benchmark: str,
    figures: list[dict[str, object]],
    *,
    title: str | None = None,
    machine: dict[str, object] | None = None,
) -> dict[str, object]:
    """A benchmark result as written to ``benchmarks/results/<name>.json``.

    ``figures`` is a list of ``{"name", "value", "unit", "note"}`` records (``unit`` and
    ``note`` optional). The record adds the machine (``machine`` if given, e.g. taken
    before the run, else :func:`describe` now), the date (UTC, ISO 8601) and the command
    that ran (``python`` and ``sys.argv``). ``docs/gen/benchmarks_page.py`` turns the
    latest record of each benchmark into the documentation's benchmarks page.
    """
    import datetime
    import shlex
    import sys

    argv = list(sys.argv)
    if argv and argv[0].endswith(".py"):
        argv[0] = os.path.relpath(argv[0]) if os.path.isabs(argv[0]) else argv[0]
    record: dict[str, object] = {
        "benchmark": benchmark,
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "command": "python " + shlex.join(argv),
        "machine": machine if machine is not None else describe(),
        "figures": figures,
    }
    if title:
        record["title"] = title
    return record


def write_result(path: str, record: dict[str, object]) -> None:
    """Write a result record as JSON, atomically (temporary name, then rename)."""
    from planetref.runtime.atomic import write_json_atomic

    write_json_atomic(path, record, indent=1)
