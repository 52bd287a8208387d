"""Helpers of the reliability battery: the CLI runners and the mini scene settings.

Each test runs the command a user would type (``CliRunner`` on ``planetref.cli.main`` or
a real subprocess) and checks three things: the exit status, that the error is exactly
one line naming the file, and that nothing the user owns changed.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

from click.testing import CliRunner

from planetref.cli import main

MINI_SCENE: dict[str, Any] = {
    "name": "mini",
    "site": {"margin_m": 150.0},
    "camera": {
        "n_samples": 64,
        "overlap_samples": 8,
        "n_lines": 96,
        "gsd_m": 1.0,
        "ccd_stagger_mm": 0.1,
    },
    "terrain": {
        "dem_gsd_m": 2.0,
        "craters": {"density_per_km2": 200.0, "d_max_m": 120.0},
        "ridges": {"count": 1, "width_m": 120.0},
    },
    "albedo": {"texture_gsd_m": 0.5},
    "reference": {"dem_pad_m": 500.0},
    "render": {"write_rpc": False, "n_checkpoints": 5, "measure_grid": 4, "chunk_pixels": 4096},
}

REPO = Path(__file__).resolve().parents[2]
SHARED = REPO.parent / "shared"
if not SHARED.is_dir():
    SHARED = Path("/work/shared")


def run_cli(*args: str) -> Any:
    """``planetref ARGS`` in process; stderr is kept apart from stdout."""
    return CliRunner().invoke(main, [str(a) for a in args])


def one_line_error(result: Any, *needles: str) -> str:
    """Assert the command failed with exactly one ``Error:`` line holding ``needles``."""
    assert result.exit_code == 1, (result.exit_code, result.stdout, result.stderr)
    # Warnings before the error are log lines of their own ("WARNING name: ..."), also
    # Python's warnings (the CLI logs them as one line each).
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert all(ln.startswith("WARNING ") for ln in lines[:-1]), lines
    lines = lines[-1:]
    assert len(lines) == 1 and lines[0].startswith("Error: "), lines
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    assert "Traceback" not in result.stderr
    return lines[0]


def run_subprocess(*args: str, timeout: float = 120.0, **kw: Any) -> subprocess.CompletedProcess:
    """``python -m planetref ARGS`` in a real process (bounded in time)."""
    env = {**os.environ, "PYTHONPATH": str(REPO / "src"), "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, "-W", "ignore", "-m", "planetref", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
        check=False,
        **kw,
    )
