import numpy as np

from planetref.geometry.rotations import (
    axis_rotation,
    rotate_to_camera,
    rotation_matrix,
    rotation_matrix_derivatives,
)


def _r0():
    # A proper rotation far from the identity.
    return rotation_matrix(0.7, -1.2, 2.5)


def test_rotate_to_camera_equals_the_transposed_matrix():
    rng = np.random.default_rng(0)
    ang = rng.uniform(-0.5, 0.5, (50, 3))
    d = rng.normal(0, 1e5, (50, 3))
    r0 = _r0()
    out = rotate_to_camera(ang[:, 0], ang[:, 1], ang[:, 2], d, r0=r0, derivatives=True)
    full = r0 @ rotation_matrix(ang[:, 0], ang[:, 1], ang[:, 2])  # (50, 3, 3)
    ref = np.einsum("mji,mj->mi", full, d)
    got = np.stack([out.u, out.v, out.w], axis=1)
    assert np.abs(got - ref).max() < 1e-9 * np.abs(d).max()
    # d/dd is (R0 R) itself, rows = input component.
    np.testing.assert_allclose(out.jacobian[:, :3], full, atol=1e-14)
    # d/dangles against the matrix derivatives.
    _, *dr = rotation_matrix_derivatives(ang[:, 0], ang[:, 1], ang[:, 2])
    for j in range(3):
        ref_j = np.einsum("mji,mj->mi", r0 @ dr[j], d)
        np.testing.assert_allclose(out.jacobian[:, 3 + j], ref_j, atol=1e-9 * np.abs(d).max())
    plain = rotate_to_camera(ang[:, 0], ang[:, 1], ang[:, 2], d, r0=r0)
    assert plain.jacobian is None and np.array_equal(plain.u, out.u)


def test_rotate_to_camera_angle_partials_finite_differences():
    rng = np.random.default_rng(1)
    ang = rng.uniform(-0.3, 0.3, (20, 3))
    d = rng.normal(0, 1.0, (20, 3))
    out = rotate_to_camera(*ang.T, d, derivatives=True)
    for j in range(3):
        h = np.zeros(3)
        h[j] = 1e-6
        p = rotate_to_camera(*(ang + h).T, d)
        m = rotate_to_camera(*(ang - h).T, d)
        fd = np.stack([p.u - m.u, p.v - m.v, p.w - m.w], axis=1) / 2e-6
        assert np.abs(fd - out.jacobian[:, 3 + j]).max() < 1e-8


def test_axis_rotations_are_right_handed_and_compose_the_photogrammetric_rotation():
    ex, ey, ez = np.eye(3)
    q = np.pi / 2
    # Right-handed: x -> y about z, y -> z about x, z -> x about y.
    np.testing.assert_allclose(axis_rotation(2, q) @ ex, ey, atol=1e-15)
    np.testing.assert_allclose(axis_rotation(0, q) @ ey, ez, atol=1e-15)
    np.testing.assert_allclose(axis_rotation(1, q) @ ez, ex, atol=1e-15)
    rng = np.random.default_rng(5)
    phi, omega, kappa = rng.uniform(-3, 3, (3, 7))
    r = axis_rotation(1, -phi) @ axis_rotation(0, omega) @ axis_rotation(2, kappa)
    np.testing.assert_allclose(r, rotation_matrix(phi, omega, kappa), atol=1e-15)
    assert axis_rotation(0, phi).shape == (7, 3, 3)
