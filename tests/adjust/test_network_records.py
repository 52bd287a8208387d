"""Networks built in code (``Network.from_records``) refuse bad records in one line.

The same checks as a network file's (``read_network``), for networks that never were a
file: lengths, names, each point's XYZ and sigmas, finite measures and sigmas, and each
measure within 1 px of its image; the message names the record (observation index and id,
or point id) and, when given, the source file.
"""

from __future__ import annotations

import numpy as np
import pytest
from adjust_synth import N_LINES, N_SAMPLES, ground_points, true_strip

from planetref.adjust import Network
from planetref.errors import InputError


@pytest.fixture(scope="module")
def records():
    cam = true_strip()
    rng = np.random.default_rng(3)
    n = 12
    line, sample = rng.uniform(0, N_LINES, n), rng.uniform(0, N_SAMPLES, n)
    xyz = ground_points(cam, np.zeros(n, int), line, sample, np.zeros(n))
    return {
        "cameras": {"strip": cam},
        "obs_camera": ["strip"] * n,
        "obs_point": [f"p{i}" for i in range(n)],
        "obs_ccd": ["ccd1"] * n,
        "line": line,
        "sample": sample,
        "point_xyz": {f"p{i}": xyz[i] for i in range(n)},
        "point_sigma_m": {f"p{i}": 5.0 for i in range(n)},
        "sigma_px": np.full(n, 0.5),
        "obs_ids": [f"m{i}" for i in range(n)],
    }


def _build(records, **change):
    kw = {**records, **change}
    cams = kw.pop("cameras")
    return Network.from_records(cams, **kw)


def _with(values, index, value):
    out = np.array(values, dtype=float)
    out[index] = value
    return out


def test_good_records_build_and_edge_measures_are_kept(records):
    net = _build(records)
    assert net.n_obs == 12 and net.n_points == 12
    # within 1 px of the edges, as network files accept
    net = _build(records, line=_with(records["line"], 2, N_LINES + 0.9))
    assert net.obs_line[2] == N_LINES + 0.9


@pytest.mark.parametrize(
    "change, message",
    [
        (
            lambda r: {"line": _with(r["line"], 4, 999999.0)},
            r"observation 4 \(id 'm4'\): line 999999, sample .* is outside image 'strip/ccd1' "
            f"\\(0 to {N_LINES} lines, 0 to {N_SAMPLES} samples",
        ),
        (
            lambda r: {"sample": _with(r["sample"], 7, -1.5)},
            r"observation 7 \(id 'm7'\): .*sample -1.5 is outside image",
        ),
        (
            lambda r: {"line": _with(r["line"], 3, np.nan)},
            r"observation 3 \(id 'm3'\): line and sample must be finite",
        ),
        (
            lambda r: {"sigma_px": _with(r["sigma_px"], 5, np.inf)},
            r"observation 5 \(id 'm5'\): sigmas must be finite and > 0 pixels",
        ),
        (
            lambda r: {"sigma_px": _with(r["sigma_px"], 0, 0.0)},
            r"observation 0 \(id 'm0'\): sigmas must be finite and > 0",
        ),
        (
            lambda r: {"point_sigma_m": {**r["point_sigma_m"], "p6": np.nan}},
            "point 'p6': sigmas must be >= 0",
        ),
        (
            lambda r: {"point_sigma_m": {**r["point_sigma_m"], "p6": -1.0}},
            "point 'p6': sigmas must be >= 0",
        ),
        (
            lambda r: {"point_sigma_m": {k: v for k, v in r["point_sigma_m"].items() if k != "p2"}},
            "no value for point 'p2'",
        ),
        (
            lambda r: {"point_xyz": {**r["point_xyz"], "p1": [1.0, 2.0]}},
            "point 'p1': expected 3 values",
        ),
        (
            lambda r: {"point_xyz": {**r["point_xyz"], "p0": [np.nan] * 3}},
            "point 'p0' is fixed or weighted but has no finite a priori XYZ",
        ),
        (lambda r: {"obs_point": [*r["obs_point"][:-1], "nowhere"]}, "unknown point 'nowhere'"),
        (lambda r: {"obs_camera": r["obs_camera"][:-1]}, "11 entries for 12 observations"),
        (lambda r: {"obs_ccd": [*r["obs_ccd"][:-1], "ccd9"]}, "has no CCD 'ccd9'"),
        (lambda r: {"point_kind": {"p0": "mcp"}}, "no kind for point 'p1'"),
    ],
)
def test_bad_record_is_one_line_naming_it(records, change, message):
    with pytest.raises(InputError, match=message) as err:
        _build(records, **change(records))
    assert "\n" not in str(err.value)
    # with a source, the file is named first
    with pytest.raises(InputError, match=message) as err:
        _build(records, **change(records), source="net/measures.csv")
    assert str(err.value).startswith("net/measures.csv: ")


def test_network_constructor_names_out_of_range_indices(records):
    net = _build(records)
    fields = {k: getattr(net, k) for k in net.__dataclass_fields__}
    bad = np.array(net.obs_point)
    bad[9] = 12
    with pytest.raises(InputError, match=r"observation 9 \(id 'm9'\): point index 12 out of range"):
        Network(**{**fields, "obs_point": bad})
    bad = np.array(net.obs_ccd)
    bad[[1, 2]] = 3
    with pytest.raises(InputError, match=r"observation 1 .*CCD index 3 out of range.*2 of 12"):
        Network(**{**fields, "obs_ccd": bad})
    with pytest.raises(InputError, match="camera index -1 out of range"):
        Network(**{**fields, "obs_camera": np.full(12, -1)})
