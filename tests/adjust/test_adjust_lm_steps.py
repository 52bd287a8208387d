"""The LM loop's pieces: the oscillation correction and the converged VCE solution."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from adjust_synth import mcp_problem

from planetref.adjust import adjust, variance
from planetref.adjust.lm_steps import oscillation_correction


def _spd(rng: np.random.Generator, n: int) -> np.ndarray:
    a = rng.normal(size=(n, n))
    return a @ a.T + n * np.eye(n)


@pytest.mark.parametrize("q", [0.9, 0.5, -0.6])
def test_correction_ends_a_geometric_sequence(q):
    """Gauss-Newton with a Hessian that misjudges one direction converges linearly there.

    The true curvature along ``u`` is ``1 + q`` times that of the model ``S``: with
    ``q > 0`` every step overshoots and the error along ``u`` is multiplied by ``-q``,
    with ``q < 0`` every step falls short (``|q|`` per step, same sign). The corrected
    step removes that error (to rounding); a plain step only shrinks it by ``|q|``.
    """
    rng = np.random.default_rng(3)
    n = 8
    s_mat = _spd(rng, n)
    u = rng.normal(size=n)
    su = s_mat @ u
    h_true = s_mat + q * np.outer(su, su) / (u @ su)
    x_star = rng.normal(size=n)

    def gn_step(x: np.ndarray) -> np.ndarray:
        return -np.linalg.solve(s_mat, h_true @ (x - x_star))

    def err(x: np.ndarray) -> float:
        return float(np.sqrt((x - x_star) @ h_true @ (x - x_star)))

    x = x_star + 5.0 * u + 1e-3 * rng.normal(size=n)
    prev = None
    for _ in range(3):  # plain steps: the other directions die out, u remains
        step = gn_step(x)
        assert oscillation_correction(step, None, s_mat) is None
        x, prev = x + step, step
    before = err(x)
    step = gn_step(x)
    corr = oscillation_correction(step, prev, s_mat)
    assert corr is not None
    assert err(x + step) == pytest.approx(abs(q) * before, rel=1e-3)
    assert err(x + step + corr) < 1e-3 * before


def test_no_correction_without_a_geometric_sequence():
    rng = np.random.default_rng(4)
    s_mat = _spd(rng, 6)
    prev = rng.normal(size=6)
    other = np.linalg.solve(s_mat, rng.normal(size=6))
    assert oscillation_correction(-0.05 * prev, prev, s_mat) is None  # ratio too small
    assert oscillation_correction(-3.0 * prev, prev, s_mat) is None  # growing
    assert oscillation_correction(0.9 * prev, prev, s_mat) is None  # > 5x extrapolation
    assert oscillation_correction(None, prev, s_mat) is None  # damped step
    # Another direction (|cos| in S's metric below 0.8).
    o = other - (other @ s_mat @ prev) / (prev @ s_mat @ prev) * prev
    assert oscillation_correction(0.5 * o + 0.1 * prev, prev, s_mat) is None
    np.testing.assert_allclose(
        -0.5 * prev + oscillation_correction(-0.5 * prev, prev, s_mat), -prev / 3.0, rtol=1e-12
    )
    np.testing.assert_allclose(
        0.5 * prev + oscillation_correction(0.5 * prev, prev, s_mat), prev, rtol=1e-12
    )


def test_vce_solution_is_the_optimum_of_its_final_weights(monkeypatch):
    """A re-weighted run stopped by the VCE's iteration cap is finished to convergence.

    With the cap at one LM iteration the re-weighted run stops short of its optimum;
    the solution handed back must still be the optimum of the final weights: the same
    network with those sigmas, adjusted without variance components from the initial
    cameras, lands on it to 1e-3 sigma.
    """
    monkeypatch.setattr(variance, "_VCE_MAX_LM", 1)
    net, _, _ = mcp_problem(300, noise_px=0.5, seed=21, ground_sigma_m=4.0)
    cfg = {"solver": {"loss": "linear"}, "outliers": {"enabled": False}}
    # One re-weighting: the run with the final weights starts where the first weights'
    # optimum was (the image sigma halves: four times the weight).
    res = adjust(net, {**cfg, "variance": {"max_iterations": 1}})
    assert res.variance["iterations"] == 1
    obs_sig = np.array(net.obs_sigma_px, float)
    pt_sig = np.array(net.point_sigma_m, float)
    ccd_names = np.asarray(net.cameras[0].ccd_names)[net.obs_ccd]
    for g in res.variance["groups"]:
        f = g["sigma_scale"]
        if g["kind"] == "image":
            sel = np.array([g["group"].endswith("/" + c) for c in ccd_names])
            assert sel.any(), g["group"]
            obs_sig[sel] *= f
        elif g["group"].endswith("planimetric"):
            pt_sig[:, :2] *= f
        elif g["group"].endswith("height"):
            pt_sig[:, 2] *= f
        else:
            pt_sig *= f
    fixed = dataclasses.replace(net, obs_sigma_px=obs_sig, point_sigma_m=pt_sig)
    again = adjust(fixed, {**cfg, "variance": {"enabled": False}})
    assert again.converged
    act = res.parameter_mode != 2
    diff = np.abs(res.x - again.x)[act] / again.sigma[act]
    assert diff.max() < 1e-3, diff.max()
