"""``planetref demo``: names checked before the scene is simulated; the cost notice."""

import pytest
from click.testing import CliRunner

import planetref.cli.simulate
import planetref.matching.registry
from planetref.cli import main
from planetref.cli.georef import DEMO_COSTS, demo_cost_notice
from planetref.matching.registry import MATCHERS
from planetref.simulate.config import DIFFICULTIES, available_presets


class _Simulated(Exception):
    """Raised by the stand-in simulator: the demo got as far as simulating."""


@pytest.fixture
def no_simulation(monkeypatch):
    """Record every call of the simulator and stop there (no minutes of simulation)."""
    calls = []

    def fake(cfg, out_dir, **kwargs):
        calls.append((cfg, out_dir))
        raise _Simulated

    monkeypatch.setattr(planetref.cli.simulate, "simulate_run", fake)
    return calls


def _demo(tmp_path, *args):
    out = tmp_path / "demo"
    r = CliRunner().invoke(main, ["demo", "--out", str(out), *args])
    return r, out


def test_unknown_matcher_fails_before_simulating(tmp_path, no_simulation):
    r, out = _demo(tmp_path, "--preset", "tiny", "--matchers", "sift,sfit")
    assert r.exit_code == 1, r.output
    assert not no_simulation and not out.exists()
    # One line naming the bad name and every valid one.
    msg = r.stderr.strip()
    assert len(msg.splitlines()) == 1 and "sfit" in msg
    assert all(name in msg for name in MATCHERS)


def test_unknown_preset_fails_before_simulating(tmp_path, no_simulation):
    r, out = _demo(tmp_path, "--preset", "tinyy", "--matchers", "sift")
    assert r.exit_code == 1, r.output
    assert not no_simulation and not out.exists()
    msg = r.stderr.strip()
    assert len(msg.splitlines()) == 1 and "tinyy" in msg
    assert all(name in msg for name in available_presets())


def test_matchers_without_weights_fail_before_simulating(tmp_path, no_simulation, monkeypatch):
    # No weight file anywhere (an installed weight package would otherwise count).
    monkeypatch.setattr(planetref.matching.registry, "missing_weights", lambda n, d: list(n))
    r, out = _demo(tmp_path, "--matchers", "disk-lightglue")
    assert r.exit_code == 1, r.output
    assert not no_simulation and not out.exists()
    msg = r.stderr.strip()
    assert "none of the matchers can run" in msg and "weights download disk-lightglue" in msg


def test_difficulties_are_the_simulators():
    from planetref.cli.georef import demo_command

    option = next(p for p in demo_command.params if p.name == "difficulty")
    assert tuple(option.type.choices) == DIFFICULTIES


def test_cost_notice_before_simulating_and_not_under_quiet(tmp_path, no_simulation):
    r, out = _demo(tmp_path, "--matchers", "sift")
    assert len(no_simulation) == 1  # the default preset and seed, simulated once
    assert no_simulation[0][0].name == "hiric-strip"
    first = r.stderr.splitlines()[0]
    assert first == demo_cost_notice("hiric-strip")
    assert "1,470 CPU seconds" in first and "2.8 GB" in first and "1.9 GB" in first
    assert "about" in first and "depends on the matchers" in first
    r = CliRunner().invoke(main, ["-q", "demo", "--out", str(out), "--matchers", "sift"])
    assert len(no_simulation) == 2 and "CPU seconds" not in r.output


def test_cost_table_covers_every_preset():
    assert set(DEMO_COSTS) == set(available_presets())
    for preset in available_presets():
        line = demo_cost_notice(preset, n_seeds=3)
        assert "\n" not in line and preset in line
    assert "per seed" in demo_cost_notice("tiny", n_seeds=3)
    assert "not known" in demo_cost_notice("hiric")
