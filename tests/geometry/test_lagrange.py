import numpy as np
import pytest

from planetref.errors import InputError
from planetref.geometry.lagrange import LagrangeWindows, lagrange_window


def test_window_polynomials_equal_weighted_sums():
    times = np.array([0.0, 0.7, 2.0, 2.6, 4.1, 5.0, 6.3])
    rng = np.random.default_rng(0)
    values = rng.normal(0, 1, (7, 6))
    win = LagrangeWindows(times, 4)
    t = np.linspace(-1.0, 7.0, 400)
    start, w, dw = win.weights(t, derivative=True)
    idx = win.window_nodes(start)
    ref = np.einsum("mk,mkp->mp", w, values[idx])
    dref = np.einsum("mk,mkp->mp", dw, values[idx])
    s2, tau = win.window(t)
    val, der = win.evaluate(win.polynomials(values), s2, tau, derivative=True)
    assert np.array_equal(s2, start)
    assert np.abs(val - ref).max() < 1e-12 and np.abs(der - dref).max() < 1e-11
    # Finite differences of the interpolant agree with its derivative.
    h = 1e-6
    vp, _ = win.evaluate(win.polynomials(values), *win.window(t + h))
    vm, _ = win.evaluate(win.polynomials(values), *win.window(t - h))
    inside = (win.window(t + h)[0] == start) & (win.window(t - h)[0] == start)
    assert np.abs((vp - vm)[inside] / (2 * h) - der[inside]).max() < 1e-6


def test_windows_clamp_to_the_ends_and_order_is_capped():
    times = np.arange(6.0)
    idx, _, _ = lagrange_window(times, np.array([-3.0, 0.2, 2.5, 5.5, 9.0]), 4)
    assert idx[:, 0].tolist() == [0, 0, 1, 2, 2]
    idx, w, _ = lagrange_window(times[:3], np.array([1.5]), 4)
    assert idx.shape == (1, 3) and w.sum() == pytest.approx(1.0)
    with pytest.raises(InputError):
        LagrangeWindows(np.array([0.0, 0.0, 1.0]), 4)
