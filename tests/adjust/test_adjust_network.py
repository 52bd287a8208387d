import csv
import json

import numpy as np
import pytest
from adjust_synth import N_LINES, N_SAMPLES, ground_points, perturb, shared_data, true_strip
from click.testing import CliRunner

from planetref.adjust import adjust
from planetref.adjust.config import validate_config
from planetref.adjust.network_file import read_network
from planetref.cli.adjust import adjust_command
from planetref.errors import InputError, MissingFileError

HEADER = [
    "point_id",
    "point_type",
    "apriori_x_m",
    "apriori_y_m",
    "apriori_z_m",
    "image_id",
    "sample",
    "line",
]


def write_network(
    tmp_path, *, n_mcp=300, n_tie=60, convention="isis", seed=0, extra_toml="", rows_hook=None
):
    """A strip (3 CCDs, one image id per CCD) with MCPs and CCD-overlap tie points."""
    true = true_strip()
    init = perturb(true)
    init.to_json(tmp_path / "strip.json")
    rng = np.random.default_rng(seed)
    rows = []
    shift = 0.5 if convention == "isis" else 0.0
    ccd = rng.integers(0, 3, n_mcp)
    line = rng.uniform(0, N_LINES, n_mcp)
    sample = rng.uniform(0, N_SAMPLES, n_mcp)
    xyz = ground_points(true, ccd, line, sample, rng.uniform(-1000, 1000, n_mcp))
    for i in range(n_mcp):
        rows.append(
            [
                f"m{i}",
                "Fixed",
                *xyz[i],
                f"img/ccd{ccd[i] + 1}",
                sample[i] + shift + rng.normal(0, 0.3),
                line[i] + shift + rng.normal(0, 0.3),
            ]
        )
    tl = rng.uniform(200, N_LINES - 200, n_tie)
    ts = rng.uniform(N_SAMPLES - 14, N_SAMPLES - 2, n_tie)
    txyz = ground_points(true, np.zeros(n_tie, int), tl, ts, np.zeros(n_tie))
    ip = true.ground_to_image(txyz, ccd="ccd2")
    for i in range(n_tie):
        approx = txyz[i] + rng.normal(0, 30, 3)
        rows.append([f"t{i}", "Free", *approx, "img/ccd1", ts[i] + shift, tl[i] + shift])
        rows.append(
            [f"t{i}", "Free", *approx, "img/ccd2", ip.sample[i] + shift, ip.line[i] + shift]
        )
    header = list(HEADER)
    if rows_hook is not None:
        header, rows = rows_hook(header, rows)
    with open(tmp_path / "measures.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)
    images = "\n".join(
        f'"img/ccd{k}" = {{ camera = "strip.json", ccd = "ccd{k}" }}' for k in (1, 2, 3)
    )
    (tmp_path / "network.toml").write_text(
        f'measures = "measures.csv"\nconvention = "{convention}"\n{extra_toml}\n'
        f"[images]\n{images}\n"
    )
    return tmp_path / "network.toml", true


def test_read_and_adjust_network(tmp_path):
    path, _true = write_network(tmp_path)
    nf = read_network(path)
    net = nf.network
    assert net.camera_ids == ("strip",)
    assert net.n_obs == 300 + 120
    assert set(net.point_kind) == {"mcp", "tie"}
    # isis -> planetref: first pixel centre 1.0 -> 0.5
    with open(tmp_path / "measures.csv") as fh:
        first = next(iter(csv.DictReader(fh)))
    assert net.obs_line[0] == pytest.approx(float(first["line"]) - 0.5)
    assert net.obs_sample[0] == pytest.approx(float(first["sample"]) - 0.5)
    # Free points get the documented default a-priori sigma (the datum cannot float).
    assert np.all(net.point_sigma_m[net.point_kind == "tie"] == 200.0)
    free = read_network(path, config={"observations": {"tie_apriori_sigma_m": None}})
    assert np.all(np.isinf(free.network.point_sigma_m[free.network.point_kind == "tie"]))
    assert np.all(net.point_sigma_m[net.point_kind == "mcp"] == 0)
    res = adjust(net, {"linescan": {"position": {"mode": "weighted", "sigma_m": 100.0}}})
    assert res.summary()["rmse_px"] < 0.5


def test_half_pixel_convention_matters(tmp_path):
    path, _ = write_network(tmp_path, convention="isis", n_tie=0)
    good = adjust(
        read_network(path).network,
        {"linescan": {"position": {"mode": "fixed"}, "attitude": {"mode": "fixed"}}},
    )
    text = path.read_text().replace('convention = "isis"', 'convention = "csm"')
    path.write_text(text)
    bad = adjust(
        read_network(path).network,
        {"linescan": {"position": {"mode": "fixed"}, "attitude": {"mode": "fixed"}}},
    )
    # Read with the wrong convention every measure is off by half a pixel in both axes.
    shift = bad.residual_initial - good.residual_initial
    np.testing.assert_allclose(shift, -0.5, atol=1e-6)


def test_adjustment_table_in_network_file(tmp_path):
    path, _ = write_network(
        tmp_path,
        extra_toml="[adjustment]\nlinescan.position = "
        '{ mode = "weighted", sigma_m = "50 m" }\n'
        'linescan.attitude = { mode = "weighted", sigma_rad = "20 arcsec" }',
    )
    nf = read_network(path)
    assert nf.config.linescan.position.sigma_m == 50.0
    assert nf.config.linescan.attitude.sigma_rad == pytest.approx(20 * np.pi / 648000)


@pytest.mark.parametrize(
    ("hook", "message"),
    [
        (lambda h, r: ([c for c in h if c != "line"], [x[:-1] for x in r]), "missing column"),
        (lambda h, r: ([*h, "colour"], [[*x, "red"] for x in r]), "unknown column"),
        (lambda h, r: (h, [[*r[0][:7], "abc"], *r[1:]]), r"field 'line': row 2: expected a number"),
        (lambda h, r: (h, [[*r[0][:5], "img/ccd9", *r[0][6:]], *r[1:]]), "row 2: image"),
        (lambda h, r: (h, [[r[0][0], "Wobbly", *r[0][2:]], *r[1:]]), "unknown point type"),
        (
            lambda h, r: (h, [*r, [r[0][0], "Fixed", "1", "2", "3", *r[0][5:]]]),
            "other a priori coordinates",
        ),
        (lambda h, r: (h, [[r[0][0], "Constrained", *r[0][2:]], *r[1:]]), "needs sigma"),
        (lambda h, r: (h, [r[0][:3], *r[1:]]), "fields for"),
    ],
)
def test_measures_errors_name_file_row_column(tmp_path, hook, message):
    path, _ = write_network(tmp_path, n_mcp=20, n_tie=0, rows_hook=hook)
    with pytest.raises(InputError, match=message) as exc:
        read_network(path)
    assert "measures.csv" in str(exc.value)


@pytest.mark.parametrize(
    ("convention", "line", "sample", "message"),
    [
        # ISIS: the image spans 0.5 .. n + 0.5; 1 px beyond an edge is refused.
        ("isis", N_LINES + 0.5 + 1.01, 100.0, r"row 2: line 3001.51 is outside .*0.5 to 3000.5"),
        ("isis", 100.0, -0.51, r"row 2: sample -0.51 is outside .*0.5 to 512.5"),
        ("csm", -1.01, 100.0, r"row 2: line -1.01 is outside .*0 to 3000\)"),
        ("csm", 100.0, N_SAMPLES + 1.01, r"row 2: sample 513.01 is outside .*0 to 512\)"),
    ],
)
def test_measure_outside_its_image_is_refused(tmp_path, convention, line, sample, message):
    def hook(h, r):
        return h, [[*r[0][:6], sample, line], *r[1:]]

    path, _ = write_network(tmp_path, n_mcp=20, n_tie=0, convention=convention, rows_hook=hook)
    with pytest.raises(InputError, match=message) as exc:
        read_network(path)
    assert "measures.csv" in str(exc.value)


@pytest.mark.parametrize(
    ("convention", "line", "sample"),
    [("isis", N_LINES + 1.49, -0.49), ("csm", -0.99, N_SAMPLES + 0.99)],
)
def test_measure_within_a_pixel_of_the_edge_is_kept(tmp_path, convention, line, sample):
    def hook(h, r):
        return h, [[*r[0][:6], sample, line], *r[1:]]

    path, _ = write_network(tmp_path, n_mcp=20, n_tie=0, convention=convention, rows_hook=hook)
    net = read_network(path).network
    shift = 0.5 if convention == "isis" else 0.0
    assert net.obs_line[0] == pytest.approx(line - shift)
    assert net.obs_sample[0] == pytest.approx(sample - shift)


def test_real_ctx_measure_outside_its_image_is_refused(tmp_path):
    """The audit's case: one CTX measure set to line 999999 was silently an outlier."""
    src = shared_data() / "ctx_syrtis"
    for f in src.iterdir():
        (tmp_path / f.name).write_bytes(f.read_bytes())
    with open(tmp_path / "measures.csv", newline="") as fh:
        rows = list(csv.reader(fh))
    rows[5][rows[0].index("line")] = "999999"  # file row 6
    with open(tmp_path / "measures.csv", "w", newline="") as fh:
        csv.writer(fh).writerows(rows)
    r = CliRunner().invoke(
        adjust_command, [str(tmp_path / "network.toml"), "--out", str(tmp_path / "out")]
    )
    assert r.exit_code != 0
    assert isinstance(r.exception, InputError)
    msg = str(r.exception)
    assert "measures.csv" in msg and "row 6: line 999999 is outside image" in msg
    assert "'MRO/CTX/0884541979:200' (0.5 to 52224.5)" in msg
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_network_file_errors(tmp_path):
    path, _ = write_network(tmp_path, n_mcp=20, n_tie=0)
    text = path.read_text()
    path.write_text(text.replace('convention = "isis"', 'convention = "pixel"'))
    with pytest.raises(InputError, match="convention"):
        read_network(path)
    path.write_text("whatever = 1\n" + text)
    with pytest.raises(InputError, match="unknown key"):
        read_network(path)
    path.write_text(text.replace("strip.json", "nope.json"))
    with pytest.raises(MissingFileError, match=r"nope.json"):
        read_network(path)
    path.write_text(text.replace('ccd = "ccd3"', 'ccd = "ccd7"'))
    with pytest.raises(InputError, match=r"no CCD 'ccd7'"):
        read_network(path)
    path.write_text(text + '\n[adjustment]\nsolver = { loss = "squared" }\n')
    with pytest.raises(InputError, match=r"solver.loss"):
        read_network(path)
    with pytest.raises(MissingFileError):
        read_network(tmp_path / "absent.toml")


def test_config_units_and_validation():
    cfg = validate_config(
        {
            "csm": {
                "pointing_offset": {"mode": "weighted", "sigma_rad": "5 urad"},
                "pointing_rate": {"mode": "weighted", "sigma_rad_s": "2 arcsec/s"},
            },
            "linescan": {"position": {"mode": "weighted", "sigma_m": "0.2 km"}},
        }
    )
    assert cfg.csm.pointing_offset.sigma_rad == pytest.approx(5e-6)
    assert cfg.csm.pointing_rate.sigma_rad_s == pytest.approx(2 * np.pi / 648000)
    assert cfg.linescan.position.sigma_m == 200.0
    with pytest.raises(InputError, match="needs sigma_rad"):
        validate_config({"linescan": {"attitude": {"mode": "weighted"}}})
    with pytest.raises(InputError, match=r"linescan.attitude.sigma_rad"):
        validate_config({"linescan": {"attitude": {"mode": "weighted", "sigma_rad": "3 furlong"}}})
    unknown = r"unknown key 'solver.max_iteration' \(valid keys: .*max_iterations"
    with pytest.raises(InputError, match=unknown):
        validate_config({"solver": {"max_iteration": 3}})


def run_cli(*args):
    return CliRunner().invoke(
        adjust_command, [str(a) for a in args], obj={"quiet": True}, catch_exceptions=False
    )


def test_cli_writes_outputs(tmp_path):
    path, _ = write_network(tmp_path, n_mcp=200, n_tie=30)
    out = tmp_path / "out"
    r = run_cli(
        path,
        "--out",
        out,
        "--solve",
        "node-attitude,node-position",
        "--set",
        'linescan.position.sigma_m="80 m"',
        "--no-rpc",
    )
    assert r.exit_code == 0, r.output
    summary = json.loads(r.output)
    report = json.loads((out / "report.json").read_text())
    adj = report["adjustment"]
    for key in ("rmse_px_before", "rmse_px", "outlier_ratio_pct", "n_total", "n_inliers"):
        assert key in adj
    assert adj == summary | {"seconds": adj["seconds"]}
    assert adj["rmse_px"] < 0.5 < adj["rmse_px_before"]
    assert report["config"]["linescan"]["position"] == {"mode": "weighted", "sigma_m": 80.0}
    assert (out / "config.toml").is_file() and (out / "config.json").is_file()
    assert (out / "cameras" / "strip.json").is_file()
    assert len(list((out / "plots").glob("residuals_strip_ccd*.png"))) == 3
    with open(out / "residuals.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 260 and {"dx_px", "dy_px", "inlier", "ccd"} <= set(rows[0])
    assert "Table 2" in (out / "report.md").read_text()
    assert "rmse_x_px" in adj and "rmse_y_px" in adj
    with open(out / "points.csv") as fh:
        pts = list(csv.DictReader(fh))
    assert len(pts) == 230 and {"shift_m", "sigma_up_m", "lat_deg"} <= set(pts[0])
    assert report["config"]["observations"]["tie_apriori_sigma_m"] == 200.0
    # --tie-sigma free and --no-vce reach the configuration.
    out2 = tmp_path / "out2"
    r = run_cli(path, "--out", out2, "--no-rpc", "--no-plots", "--tie-sigma", "free", "--no-vce")
    assert r.exit_code == 0, r.output
    rep2 = json.loads((out2 / "report.json").read_text())
    assert rep2["config"]["observations"]["tie_apriori_sigma_m"] is None
    assert rep2["variance_components"]["enabled"] is False
    # A non-empty --out is refused without --overwrite.
    # (The planetref click group turns these errors into one-line messages.)
    r = CliRunner().invoke(adjust_command, [str(path), "--out", str(out)], obj={})
    assert isinstance(r.exception, InputError) and "--overwrite" in str(r.exception)
    r = CliRunner().invoke(
        adjust_command, [str(path), "--out", str(out), "--overwrite", "--solve", "wings"], obj={}
    )
    assert isinstance(r.exception, InputError) and "unknown" in str(r.exception)


def test_tile_id_column(tmp_path):
    """A network file's ``tile_id`` column gives each measure its tile, per image camera;
    an empty cell (the tie points here) is no tile, and the adjustment estimates the
    tiles' offset sigma (Constrained MCPs: the consider terms need unknown points)."""

    def hook(header, rows):
        out = []
        for r in rows:
            mcp = r[0].startswith("m")
            tile = f"T{int(float(r[7]) // 1000)}" if mcp else ""
            typ = "Constrained" if mcp else r[1]
            out.append([r[0], typ, *r[2:], tile, "1.0" if mcp else ""])
        return [*header, "tile_id", "sigma_x_m"], out

    def hook3(header, rows):
        h, out = hook(header, rows)
        h += ["sigma_y_m", "sigma_z_m"]
        return h, [[*r, r[-1], r[-1]] for r in out]

    path, _ = write_network(tmp_path, rows_hook=hook3)
    net = read_network(path).network
    mcp = net.point_kind[net.obs_point] == "mcp"
    assert np.all(net.obs_tile[~mcp] == -1)
    # The same tile id on every CCD of one camera is one tile (ids are per camera).
    assert sorted(np.unique(net.obs_tile[mcp]).tolist()) == [0, 1, 2]
    with open(tmp_path / "measures.csv") as fh:
        first = next(iter(csv.DictReader(fh)))
    assert net.obs_tile[0] == 0 and first["tile_id"] == "T" + str(int(float(first["line"]) // 1000))
    res = adjust(net)
    assert res.consider is not None and res.consider.tile is not None
    assert res.consider.tile.n_tiles == 3
    assert 0.0 <= res.consider.tile.sigma_px[0] < 0.3  # no tile offsets in these data
    # `planetref adjust` reports the estimate.
    out = tmp_path / "out"
    r = run_cli(path, "--out", out, "--no-rpc", "--no-plots")
    assert r.exit_code == 0, r.output
    sysm = json.loads((out / "report.json").read_text())["systematic"]
    assert sysm["n_tile_offsets"] == 3 and sysm["tile_offset_source"] == "estimated"
    assert sysm["tile_offset_sigma_px"] == list(res.consider.tile.sigma_px)
