"""The parameter-correlation warning: adjacent-node angle pairs are expected, others not."""

import numpy as np

from planetref.adjust.config import DiagnosticsConfig
from planetref.adjust.diagnostics import correlation_warnings


def _corr(names, pairs):
    c = np.eye(len(names))
    for a, b, v in pairs:
        i, j = names.index(a), names.index(b)
        c[i, j] = c[j, i] = v
    return c


NAMES = [
    f"strip1:node{i}.{p}" for i in range(4) for p in ("X", "Y", "Z", "phi", "omega", "kappa")
] + ["strip2:node0.kappa", "strip2:node1.kappa", "strip1:interior.f"]


def test_adjacent_node_angles_are_reported_but_do_not_warn():
    cfg = DiagnosticsConfig()
    corr = _corr(
        NAMES,
        [
            ("strip1:node0.kappa", "strip1:node1.kappa", 0.99990),
            ("strip1:node1.phi", "strip1:node2.phi", -0.9995),
            ("strip2:node0.kappa", "strip2:node1.kappa", 0.9993),
            ("strip1:node0.X", "strip1:node0.Y", 0.5),
        ],
    )
    info, warnings = correlation_warnings(NAMES, corr, cfg)
    assert warnings == []
    assert info["n_pairs_above"] == 3
    assert info["n_adjacent_node_pairs"] == 3
    assert info["n_other_pairs"] == 0
    assert info["largest"] == ["strip1:node0.kappa", "strip1:node1.kappa", 0.9999]


def test_other_high_correlations_still_warn():
    cfg = DiagnosticsConfig()
    corr = _corr(
        NAMES,
        [
            ("strip1:node0.kappa", "strip1:node1.kappa", 0.99995),  # expected, excluded
            ("strip1:node0.kappa", "strip1:node2.kappa", 0.9960),  # two nodes apart
            ("strip1:node1.X", "strip1:node2.X", 0.9950),  # positions, not angles
            ("strip1:node3.phi", "strip1:node3.omega", 0.9930),  # two angles, one node
            ("strip1:node3.kappa", "strip2:node0.kappa", 0.9990),  # two strips
            ("strip1:node2.Z", "strip1:interior.f", -0.9992),  # self-calibration
        ],
    )
    info, warnings = correlation_warnings(NAMES, corr, cfg)
    assert info["n_pairs_above"] == 6
    assert info["n_adjacent_node_pairs"] == 1
    assert info["n_other_pairs"] == 5
    assert info["largest"][2] == 0.99995
    assert info["largest_other"] == ["strip1:node2.Z", "strip1:interior.f", -0.9992]
    assert len(warnings) == 1
    assert warnings[0].startswith("5 parameter pair(s) correlate above 0.99")
    assert "strip1:node2.Z and strip1:interior.f" in warnings[0]
    assert "1 pair(s) of the same angle at adjacent nodes" in warnings[0]


def test_no_pairs_above_threshold():
    info, warnings = correlation_warnings(NAMES, np.eye(len(NAMES)), DiagnosticsConfig())
    assert info == {"n_pairs_above": 0, "threshold": 0.99}
    assert warnings == []


def test_one_angle_at_several_nodes_is_a_note_anything_else_a_warning():
    """What the log shows: the interpolation's coupling of one angle of one camera
    across nodes is a note (INFO); a pair of two kinds of parameter stays a WARNING."""
    from planetref.adjust.evaluation import _interpolation_only

    cfg = DiagnosticsConfig()
    coupled = [
        ("strip1:node0.kappa", "strip1:node1.kappa", 0.99995),  # adjacent: not counted
        ("strip1:node0.kappa", "strip1:node2.kappa", 0.9960),  # two nodes apart
        ("strip1:node1.phi", "strip1:node3.phi", 0.9930),
    ]
    info, warnings = correlation_warnings(NAMES, _corr(NAMES, coupled), cfg)
    assert info["n_other_pairs"] == 2 and info["n_same_angle_node_pairs"] == 2
    assert len(warnings) == 1 and _interpolation_only(info)
    mixed = [*coupled, ("strip1:node3.kappa", "strip2:node0.kappa", 0.9990)]
    info, warnings = correlation_warnings(NAMES, _corr(NAMES, mixed), cfg)
    assert info["n_other_pairs"] == 3 and info["n_same_angle_node_pairs"] == 2
    assert len(warnings) == 1 and not _interpolation_only(info)


def test_points_beyond_their_sigmas_warn_only_beyond_chance():
    from planetref.adjust.diagnostics import point_summary

    n = 1000
    rng = np.random.default_rng(3)
    shift_sigma = np.abs(rng.normal(0.0, 1.0, n))  # Gaussian a-priori errors, 1 axis each
    table = {
        "kind": np.array(["tie"] * n),
        "point_id": np.array([f"t{i}" for i in range(n)]),
        "shift_m": shift_sigma * 10.0,
        "shift_up_m": np.zeros(n),
        "shift_horizontal_m": shift_sigma * 10.0,
        "shift_sigma": shift_sigma,
        "sigma_apriori": np.full((n, 1), 10.0),
    }
    used = np.ones(n, bool)
    cfg = DiagnosticsConfig()
    # ~2.7 of 1000 Gaussian values exceed 3 sigma by chance: a note, not a warning.
    _, warnings, notes = point_summary(table, used, cfg)
    assert warnings == [] and len(notes) == 1 and "by chance" in notes[0]
    table["shift_sigma"] = np.r_[shift_sigma[:-20], np.full(20, 8.0)]  # 20 blunders
    _, warnings, notes = point_summary(table, used, cfg)
    assert notes == [] and len(warnings) == 1 and warnings[0].startswith("2")
