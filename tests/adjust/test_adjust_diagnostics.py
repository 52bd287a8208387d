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
