"""--scheduler: ranges checked, sizes bounded, connections bounded in time."""

from __future__ import annotations

import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from reliability_helpers import REPO, one_line_error, run_cli

from planetref.errors import InputError
from planetref.runtime.execute import CONNECT_TIMEOUT_S, DaskExecutor, make_executor


@pytest.mark.parametrize(
    ("spec", "needle"),
    [
        ("tcp://127.0.0.1:99999", "port 99999 is outside 1-65535"),
        ("tcp://127.0.0.1:0", "port 0 is outside 1-65535"),
        ("pool:1e20", "unknown scheduler"),
        ("pool:100000000000000000000", "unknown scheduler"),
        ("pool:5000", "needs 1 <= N <= 4096"),
        ("dask-local:100000", "needs 1 <= N <= 4096"),
        ("tcp://127.0.0.1:8786?timeout=-1", "timeout=-1"),
        ("tcp://127.0.0.1:8786?timeout=nan", "timeout=nan"),
    ],
)
def test_bad_scheduler_specs_are_one_line(spec: str, needle: str, tmp_path: Path) -> None:
    # planetref georef scene --matcher sift --out run --scheduler SPEC
    with pytest.raises(InputError, match="scheduler"):
        make_executor(spec)
    r = run_cli(
        "georef", tmp_path, "--matcher", "sift", "--out", tmp_path / "o", "--scheduler", spec
    )
    one_line_error(r, needle)
    assert not (tmp_path / "o").exists()


def test_timeout_setting_is_parsed() -> None:
    ex = make_executor("tcp://10.0.0.5:8786?timeout=2.5")
    assert isinstance(ex, DaskExecutor)
    assert ex.address == "tcp://10.0.0.5:8786" and ex.connect_timeout_s == 2.5
    assert make_executor("tcp://10.0.0.5:8786").connect_timeout_s == CONNECT_TIMEOUT_S == 10.0


_CONNECT = textwrap.dedent(
    """
    import sys
    from planetref.runtime.execute import make_executor, SchedulerError
    try:
        make_executor(sys.argv[1]).client
    except SchedulerError as exc:
        print(exc)
        sys.exit(3)
    """
)


def _connect(spec: str) -> subprocess.CompletedProcess:
    """Connect in a real process, killed after 90 s: a hang fails the test, not CI."""
    return subprocess.run(
        [sys.executable, "-W", "ignore", "-c", _CONNECT, spec],
        capture_output=True,
        text=True,
        timeout=90,
        env={"PYTHONPATH": str(REPO / "src"), "PATH": "/usr/bin:/bin"},
        check=False,
    )


def test_a_listener_that_never_answers_times_out() -> None:
    # planetref georef ... --scheduler tcp://127.0.0.1:PORT?timeout=1 (a silent listener)
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen(8)  # accepts connections in the kernel, never speaks
        port = silent.getsockname()[1]
        r = _connect(f"tcp://127.0.0.1:{port}?timeout=1")
    assert r.returncode == 3, (r.stdout, r.stderr)
    assert f"no answer from the Dask scheduler tcp://127.0.0.1:{port} within 1 s" in r.stdout


def test_a_refused_port_fails_at_once() -> None:
    # planetref georef ... --scheduler tcp://127.0.0.1:PORT (nothing listens there)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    r = _connect(f"tcp://127.0.0.1:{port}")
    assert r.returncode == 3, (r.stdout, r.stderr)
    assert "cannot connect to the Dask scheduler" in r.stdout
    assert "refused" in r.stdout.lower()
