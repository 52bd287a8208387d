import numpy as np
import pytest

from planetref.geometry.roots import bracket_first_sign_change, refine_bracketed

# f_i(x) = (x - r_i) (1 + 0.3 (x - r_i)^2) + c_i: one real root per row (monotonic).
R = np.array([-3.3, 0.0, 1.2345678, 7.9, 2.0])
C = np.array([0.0, 0.5, -2.0, 0.0, 1e3])  # the last row has its root far off the grid


def f(x, rows):
    d = x - R[rows]
    return d * (1 + 0.3 * d**2) + C[rows]


def fs(x, rows):
    d = x - R[rows]
    return f(x, rows), 1 + 0.9 * d**2


def true_roots():
    out = []
    for r, c in zip(R, C, strict=True):
        poly = np.poly1d([0.3, 0.0, 1.0, c])
        real = [z.real for z in poly.r if abs(z.imag) < 1e-9]
        out.append(r + real[0])
    return np.array(out)


@pytest.mark.parametrize("slope", [True, False])
def test_bracket_and_refine_find_every_root_on_the_grid(slope):
    grid = np.linspace(-10.0, 10.0, 9)
    br = bracket_first_sign_change(f, grid, len(R))
    assert br.found.tolist() == [True, True, True, True, False]
    kw = {"residual_with_slope": fs} if slope else {"residual": f}
    x = refine_bracketed(br, xtol=1e-12, ftol=1e-9, **kw)
    truth = true_roots()
    assert np.abs(x[:4] - truth[:4]).max() < 1e-9
    assert np.isnan(x[4])


def test_refine_rejects_a_residual_above_ftol():
    # A discontinuous "residual" with a sign change but no root: bisection closes in on
    # the jump and the final residual check rejects it.
    def step(x, rows):
        return np.where(x < 0.3, -1.0, 1.0)

    br = bracket_first_sign_change(step, np.linspace(-1.0, 1.0, 5), 1)
    assert br.found[0]
    x = refine_bracketed(br, residual=step, xtol=1e-10, ftol=1e-6)
    assert np.isnan(x[0])


def test_refine_needs_exactly_one_residual():
    br = bracket_first_sign_change(f, np.linspace(-10, 10, 5), len(R))
    with pytest.raises(ValueError):
        refine_bracketed(br)


def test_stop_at_ftol_accepts_a_noisy_residual():
    # Rounding noise of 1e-10 around the root: steps never fall below xtol = 1e-15, so
    # only the residual test ends the iteration; the root is still within 1e-9.
    def noisy(x, rows):
        return (x - 0.3) + 1e-10 * np.sin(1e12 * x)

    br = bracket_first_sign_change(noisy, np.linspace(-1.0, 1.0, 5), 1)
    x = refine_bracketed(br, residual=noisy, xtol=1e-15, ftol=1e-9, stop_at_ftol=True)
    assert abs(x[0] - 0.3) < 2e-9


@pytest.mark.parametrize("slope", [True, False])
def test_a_root_on_a_grid_node_with_rounding_of_the_other_sign_is_found(slope):
    # The root is 1e-12 above the grid node 0.5, but the residual evaluated exactly at the
    # node has the other sign (rounding noise, as a camera's offset at a search-grid line):
    # the bracket is [0, 0.5] and the converged Newton point lies 1e-12 beyond its end.
    # It must be returned, not replaced by the bracket's midpoint (and then rejected).
    def noisy(x, rows):
        return (x - 0.5 - 1e-12) + 2e-12 * (x == 0.5)

    def noisy_slope(x, rows):
        return noisy(x, rows), np.ones_like(x)

    br = bracket_first_sign_change(noisy, np.linspace(-1.0, 1.0, 5), 1)
    assert br.found[0] and br.hi[0] == 0.5
    kw = {"residual_with_slope": noisy_slope} if slope else {"residual": noisy}
    x = refine_bracketed(br, xtol=1e-8, ftol=1e-6, **kw)
    assert abs(x[0] - 0.5) < 1e-11
