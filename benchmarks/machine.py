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
