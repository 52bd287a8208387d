"""RPC00B terms and their derivatives, all generated from one table of monomials."""

from __future__ import annotations

import numpy as np
import pytest

from planetref.camera.rpc.terms import terms, terms_dh, terms_dl, terms_dp


def test_terms_in_rpc00b_order():
    L, P, H = 0.3, -0.7, 1.9
    # NITF RPC00B / GDAL RPCComputeTerms, written out independently
    expected = [1, L, P, H, L * P, L * H, P * H, L**2, P**2, H**2, P * L * H, L**3]
    expected += [L * P**2, L * H**2, L**2 * P, P**3, P * H**2, L**2 * H, P**2 * H, H**3]
    np.testing.assert_allclose(terms(L, P, H), expected, rtol=1e-15)


@pytest.mark.parametrize(("derivative", "axis"), [(terms_dl, 0), (terms_dp, 1), (terms_dh, 2)])
def test_derivatives_match_finite_differences(derivative, axis):
    rng = np.random.default_rng(3)
    lph = rng.uniform(-1.2, 1.2, (3, 50))
    step = np.zeros((3, 1))
    step[axis] = 1e-6
    numeric = (terms(*(lph + step)) - terms(*(lph - step))) / 2e-6
    analytic = derivative(*lph)
    assert analytic.shape == (50, 20)
    np.testing.assert_allclose(analytic, numeric, atol=1e-8)
    assert np.all(analytic[:, 0] == 0.0)
