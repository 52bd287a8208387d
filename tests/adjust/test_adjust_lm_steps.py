"""The LM loop's pieces: Anderson steps and the converged VCE solution."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from adjust_synth import mcp_problem

from planetref.adjust import adjust, variance
from planetref.adjust.lm_steps import anderson_correction


def _spd(rng: np.random.Generator, n: int) -> np.ndarray:
    a = rng.normal(size=(n, n))
    return a @ a.T + n * np.eye(n)


def _misjudged(rng: np.random.Generator, n: int, qs: list[float]):
    """A model ``S`` and a true Hessian that differ along ``len(qs)`` directions.

    Along each direction ``u`` the true curvature is ``1 + q`` times the model's:
    Gauss-Newton steps with ``S`` multiply the error there by ``-q`` (``q > 0``: every
    step overshoots, ``q < 0``: every step falls short).
    """
    s_mat = _spd(rng, n)
    h_true = s_mat.copy()
    for q in qs:
        u = rng.normal(size=n)
        su = s_mat @ u
        h_true += q * np.outer(su, su) / (u @ su)
    return s_mat, h_true


def _run(s_mat, h_true, x_star, x, n_plain):
    """``n_plain`` plain Gauss-Newton steps from ``x``: the history, the iterate, its step."""
    history = []
    for _ in range(n_plain):
        step = -np.linalg.solve(s_mat, h_true @ (x - x_star))
        history.append((x, step))
        x = x + step
    return history, x, -np.linalg.solve(s_mat, h_true @ (x - x_star))


@pytest.mark.parametrize("qs", [[0.9], [0.5], [-0.6], [0.9, -0.8]])
def test_anderson_step_ends_linear_convergence(qs):
    """Where Gauss-Newton converges linearly, the combined step lands at the limit.

    Plain steps shrink the error only by ``max |q|`` per step (0.5-0.9 here); after three
    plain steps the Anderson step removes it to rounding, also with two slow directions
    of different ratios (where one-direction extrapolation could not).
    """
    rng = np.random.default_rng(3)
    n = 8
    s_mat, h_true = _misjudged(rng, n, qs)
    x_star = rng.normal(size=n)

    def err(x: np.ndarray) -> float:
        return float(np.sqrt((x - x_star) @ h_true @ (x - x_star)))

    history, x, step = _run(s_mat, h_true, x_star, x_star + 5.0 * rng.normal(size=n), 12)
    before = err(x)
    assert err(x + step) > 0.4 * before  # a plain step: linear convergence
    corr = anderson_correction(history, x, step, s_mat)
    assert corr is not None
    assert err(x + step + corr) < 1e-6 * before


def test_no_anderson_step_where_gauss_newton_is_fast_or_diverging():
    rng = np.random.default_rng(4)
    n = 6
    s_mat, h_true = _misjudged(rng, n, [0.05])  # nearly exact model: fast convergence
    x_star = rng.normal(size=n)
    history, x, step = _run(s_mat, h_true, x_star, x_star + rng.normal(size=n), 2)
    assert anderson_correction(history, x, step, s_mat) is None  # ratio below 0.2
    assert anderson_correction([], x, step, s_mat) is None  # no earlier step
    assert anderson_correction(history, x, None, s_mat) is None  # a damped step
    f = history[-1][1]
    assert anderson_correction(history, x, -3.0 * f, s_mat) is None  # steps growing


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
