"""The difficulty ladder's effects: each is present, measurable and seeded."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from planetref.simulate.config import DIFFICULTIES, STRESS_LADDER, load_config, load_difficulty_dict
from planetref.simulate.mismatch import best_fit_residuals
from planetref.simulate.mosaic import MosaicSource
from planetref.simulate.orbit import build_strip_cameras
from planetref.simulate.scene import build_scene_model, simulate_scene, stream


def _cameras(cfg):  # type: ignore[no-untyped-def]
    return build_strip_cameras(cfg, cfg.strips[0], stream(0, "strip", 0), stream(0, "mismatch", 0))


@pytest.mark.parametrize("difficulty", DIFFICULTIES)
def test_truth_is_not_representable_by_the_initial_model_tiny(difficulty: str) -> None:
    """The best fit of the estimated model to exact truth observations leaves >= 0.3 px."""
    cfg = load_config("tiny", difficulty=difficulty)
    sc = _cameras(cfg)
    fit = best_fit_residuals(sc.truth, sc.initial)
    assert fit["max_px"] >= 0.3, fit["ccds"]
    # ... while the same fit reaches the truth when the truth has the estimated model.
    exact = best_fit_residuals(sc.initial, sc.initial)
    assert exact["max_px"] < 1e-3


@pytest.mark.slow
@pytest.mark.parametrize("preset", ["hiric-strip", "hiric"])
@pytest.mark.parametrize("difficulty", [None, "easy", "hard"])
def test_truth_is_not_representable_by_the_initial_model(preset: str, difficulty: str) -> None:
    cfg = load_config(preset, difficulty=difficulty)
    sc = _cameras(cfg)
    fit = best_fit_residuals(sc.truth, sc.initial, n_lines=49, n_samples=9)
    assert fit["max_px"] >= 0.3, fit["ccds"]


def test_truth_ccd_placement_is_what_the_metadata_says(mini_config) -> None:  # type: ignore[no-untyped-def]
    no_lens = {"radial_k1_px": 0.0, "radial_k2_px": 0.0, "decentering_px": 0.0}
    cfg = mini_config(
        truth_mismatch={
            "ccd_offset_px": 3.0,
            "ccd_rotation_urad": 2000.0,
            "ccd_scale_ppm": 500.0,
            **no_lens,
        }
    )
    sc = _cameras(cfg)
    for nominal, true, fact in zip(
        sc.initial.ccds, sc.truth.ccds, sc.mismatch["ccds"], strict=True
    ):
        p = nominal.pixel_pitch_mm
        n = nominal.n_samples
        # Centres of the arrays differ by the drawn offsets (pixels).
        cn = np.array(nominal.focal_plane(0.5 * n))
        ct = np.array(true.focal_plane(0.5 * n))
        d = (ct - cn) / p
        assert d[0] == pytest.approx(fact["offset_along_px"], abs=1e-6)
        assert d[1] == pytest.approx(fact["offset_across_px"], abs=1e-6)
        assert (true.angle_rad - nominal.angle_rad) * 1e6 == pytest.approx(fact["rotation_urad"])
        assert (true.pixel_pitch_mm / p - 1) * 1e6 == pytest.approx(fact["scale_ppm"])
    # The line-rate error is the configured one.
    cfg = mini_config(truth_mismatch={"line_rate_error_ppm": 400.0})
    sc = _cameras(cfg)
    ratio = (
        sc.truth.line_rates.period(np.array([10.0]))[0]
        / sc.initial.line_rates.period(np.array([10.0]))[0]
    )
    assert (ratio - 1) * 1e6 == pytest.approx(400.0, rel=1e-9)


def test_oscillation_moves_the_truth_by_its_amplitude(mini_config) -> None:  # type: ignore[no-untyped-def]
    """A 20 m cross-track position oscillation shows as 20 m of ground displacement."""
    zero = {"ccd_offset_px": 0.0, "ccd_rotation_urad": 0.0, "ccd_scale_ppm": 0.0}
    # (the mini strip is 96 lines long: truth nodes every 4 lines carry a 32-line period)
    base = mini_config(
        orbit={"truth_node_spacing_lines": 4},
        jitter=[],
        truth_mismatch={
            **zero,
            "position_oscillation_m": [0, 0, 0],
            "attitude_oscillation_urad": [0, 0, 0],
            "line_rate_error_ppm": 0.0,
        },
    )
    osc = mini_config(
        orbit={"truth_node_spacing_lines": 4},
        jitter=[],
        truth_mismatch={
            **zero,
            "position_oscillation_m": [0, 20.0, 0],
            "attitude_oscillation_urad": [0, 0, 0],
            "line_rate_error_ppm": 0.0,
        },
    )
    a, b = _cameras(base), _cameras(osc)
    lines = np.linspace(0.5, 95.5, 200)
    pa = a.truth.image_to_ground(lines, np.full(200, 32.0), 0.0, ccd="ccd2")
    pb = b.truth.image_to_ground(lines, np.full(200, 32.0), 0.0, ccd="ccd2")
    t = a.truth.line_rates.time(lines)
    phase = b.mismatch["oscillation_phase_rad"][1]
    expected = 20.0 * np.sin(2 * np.pi * t / b.mismatch["oscillation_period_s"] + phase)
    got = np.linalg.norm(pb - pa, axis=1) * np.sign(expected)
    np.testing.assert_allclose(got, expected, atol=0.3)  # node interpolation: ~1 %


def test_mosaic_source_offsets_and_warps_are_where_the_metadata_says(mini_config) -> None:  # type: ignore[no-untyped-def]
    """A bright spot lands at its true place plus the source's displacement d_s."""
    from planetref.simulate.config import SunConfig
    from planetref.simulate.photometry import RadianceModel, ShadingFields
    from planetref.simulate.reference import finish_ortho, ortho_radiance

    cfg = mini_config(
        reference={"ortho_sensor": {"read_noise_e": 0.0, "bit_depth": 16, "full_well_e": 60000.0}}
    )
    sm = build_scene_model(cfg)
    grid = sm.grid
    flat = np.zeros(grid.shape, np.float32)
    albedo = np.full(grid.shape, 0.02, np.float32)
    r0, c0 = grid.rows // 2 + 7, grid.cols // 2 - 11
    albedo[r0 : r0 + 3, c0 : c0 + 3] = 0.9
    fields = ShadingFields(grid, flat, albedo, np.zeros(grid.shape), flat)
    phot = cfg.photometry
    model = RadianceModel(fields, sm.tiles, phot.reference_sun, phot, cfg.albedo, 0.0)
    waves = np.array([[2 * np.pi / 900.0, 2 * np.pi / 1300.0, 4.0, -3.0, 0.7]])
    src = MosaicSource(
        0, SunConfig(azimuth_deg=250.0, elevation_deg=34.0), 0.0, 1.0, (7.5, -6.0), waves
    )
    rel = np.zeros(sm.ortho_grid.shape, np.float32)
    ortho_radiance(sm.ortho_grid, sm.ref, sm.local, model, cfg.reference, rel, source=src)
    ortho = finish_ortho(rel, cfg.reference, np.random.default_rng(0)).astype(float)
    x = grid.x0 + (c0 + 1.5) * grid.res
    y = grid.y0 - (r0 + 1.5) * grid.res
    lon, lat = sm.local.map_to_lonlat(np.array([x]), np.array([y]))
    ex, ey = sm.ref.lonlat_to_map(lon, lat)
    dx, dy = src.displacement(ex, ey)
    assert np.hypot(dx[0], dy[0]) > 5.0  # the test means something
    og = sm.ortho_grid
    win = ortho - np.median(ortho)
    rows, cols = np.nonzero(win > 0.05 * win.max())
    w = win[rows, cols]
    cx = og.x0 + (np.average(cols, weights=w) + 0.5) * og.res
    cy = og.y0 - (np.average(rows, weights=w) + 0.5) * og.res
    assert abs(cx - (ex[0] + dx[0])) < 0.6 and abs(cy - (ey[0] + dy[0])) < 0.6


def test_mola_tracks_carry_their_offsets_and_are_interpolated_between() -> None:
    from planetref.simulate.config import ReferenceConfig
    from planetref.simulate.reference import gridded_tracks

    cfg = ReferenceConfig(
        dem_noise_m=0.0,
        mola={
            "tracks": True,
            "track_spacing_m": 1000.0,
            "shot_spacing_m": 100.0,
            "track_azimuth_deg": 0.0,
            "track_offset_m": 5.0,
            "track_tilt_m": 0.0,
        },
    )
    xx, yy = np.meshgrid(np.arange(0.0, 5000.0, 50.0), np.arange(0.0, 5000.0, 50.0))
    rec: dict = {}
    h = gridded_tracks(xx, yy, lambda x, y: np.zeros_like(x), cfg, np.random.default_rng(3), rec)
    across = np.array(rec["tracks"]["across_m"])  # x of the (north-south) tracks
    off = np.array(rec["tracks"]["offset_m"])
    # Between two neighbouring tracks the DEM is the linear interpolation of their offsets.
    k = int(np.searchsorted(across, 2500.0))
    x_mid = 0.5 * (across[k - 1] + across[k])
    col = int(np.argmin(np.abs(xx[0] - x_mid)))
    f = (xx[0, col] - across[k - 1]) / (across[k] - across[k - 1])
    expected = (1 - f) * off[k - 1] + f * off[k]
    np.testing.assert_allclose(h[10:-10, col], expected, atol=1e-6)
    assert np.std(off) > 1.0


def test_areoid_lowers_the_reference_heights(mini_config) -> None:  # type: ignore[no-untyped-def]
    from planetref.simulate.reference import reference_dem

    sm = build_scene_model(mini_config())
    rc = sm.cfg.reference
    args = (sm.dem_grid, sm.ref, sm.local, sm.coarse_grid, sm.terrain.regional_composite)
    plain = reference_dem(*args, rc, np.random.default_rng(1))
    are = rc.model_copy(
        update={"mola": rc.mola.model_copy(update={"areoid": True, "areoid_offset_m": 250.0})}
    )
    rec: dict = {}
    lowered = reference_dem(*args, are, np.random.default_rng(1), rec)
    np.testing.assert_allclose(plain - lowered, 250.0, atol=1e-3)
    assert rec["areoid"]["offset_m"] == 250.0


def test_surface_change_is_in_the_images_only(mini_config) -> None:  # type: ignore[no-untyped-def]
    cfg = mini_config(
        albedo={"reference_change": 0.0},
        surface_change={
            "new_crater_density_per_km2": 60.0,
            "new_crater_d_min_m": 10.0,
            "new_crater_d_max_m": 30.0,
            "dust_devil_tracks_per_km2": 10.0,
            "dust_devil_width_m": 10.0,
            "dust_devil_contrast": 0.2,
        },
    )
    sm = build_scene_model(cfg)
    t, g = sm.terrain, sm.grid
    ch = sm.change
    assert len(ch.new_craters) > 2 and len(ch.tracks) > 2
    dh = t.height - t.height_reference
    # New craters: a floor about 0.2 D deep (minus the rim) where each one is ...
    r, c = g.to_index(ch.new_craters.x, ch.new_craters.y)
    inside = (r > 0) & (r < g.rows - 1) & (c > 0) & (c < g.cols - 1)
    centre = dh[r[inside].astype(int), c[inside].astype(int)]
    assert np.all(centre < -0.08 * ch.new_craters.diameter_m[inside])
    # ... and nothing changed far from them.
    far = np.ones(g.shape, bool)
    for x, y, d in zip(ch.new_craters.x, ch.new_craters.y, ch.new_craters.diameter_m, strict=True):
        rr, cc = g.to_index(np.array([x]), np.array([y]))
        ext = int(2.5 * d / g.res) + 2
        far[
            max(0, int(rr[0]) - ext) : int(rr[0]) + ext, max(0, int(cc[0]) - ext) : int(cc[0]) + ext
        ] = False
    assert np.abs(dh[far]).max() == 0.0
    # Dust-devil tracks darken the images' albedo on their centre lines by the contrast.
    ratio = t.albedo.astype(np.float32) / t.albedo_reference.astype(np.float32)
    pts = np.concatenate(ch.tracks)
    r, c = g.to_index(pts[:, 0], pts[:, 1])
    ok = (r >= 0) & (r < g.rows) & (c >= 0) & (c < g.cols)
    on = ratio[r[ok].astype(int), c[ok].astype(int)]
    assert np.median(on) == pytest.approx(0.8, abs=0.05)
    assert np.median(ratio[far]) == pytest.approx(1.0, abs=1e-3)


def test_dunes_migrate_by_the_configured_distance(mini_config) -> None:  # type: ignore[no-untyped-def]
    cfg = mini_config(
        terrain={"dunes": {"fraction": 0.6, "wind_azimuth_deg": 90.0, "wavelength_m": 40.0}},
        surface_change={"dune_migration_m": 6.0},
    )
    sm = build_scene_model(cfg)
    t, g = sm.terrain, sm.grid
    assert sm.change.dune_shift_m[0] == pytest.approx(6.0)
    # Eastward wind: the reference's dunes are the current ones 6 m (3 cells) further west.
    w = t.dunes.astype(np.float32) > 0.99
    shifts = range(-6, 7)
    err = []
    for s in shifts:
        a = t.height_reference[:, 10:-10]
        b = np.roll(t.height, -s, axis=1)[:, 10:-10]
        m = w[:, 10:-10]
        err.append(float(np.mean((a[m] - b[m]) ** 2)))
    assert list(shifts)[int(np.argmin(err))] * g.res == pytest.approx(6.0)


def test_hard_scene_is_seeded_and_records_its_effects(mini_config, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    from planetref.simulate.config import load_difficulty_dict, merge_overrides

    hard = merge_overrides(load_difficulty_dict("hard"), {})
    cfg = mini_config(
        seed=3,
        **{k: v for k, v in hard.items() if k != "reference"},
        reference={"mosaic": hard["reference"]["mosaic"], "mola": hard["reference"]["mola"]},
    )
    a, b = tmp_path / "a", tmp_path / "b"
    simulate_scene(cfg, a)
    simulate_scene(cfg, b)
    for p in sorted(a.rglob("*")):
        if p.is_file():
            assert p.read_bytes() == (b / p.relative_to(a)).read_bytes(), p
    ref = json.loads((a / "truth" / "reference.json").read_text())
    assert len(ref["mosaic"]["sources"]) == 3 and "tracks" in ref
    offs = np.array([s["offset_m"] for s in ref["mosaic"]["sources"]])
    assert np.all(np.isfinite(offs)) and np.abs(offs).max() > 0
    err = json.loads((a / "truth" / "errors.json").read_text())
    assert len(err["strip1"]["truth_mismatch"]["ccds"]) == 3


def test_parallel_rendering_gives_the_same_image(mini_config, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """Blocks rendered by 2 forked workers are byte-identical to the in-process ones."""
    import warnings

    import rasterio
    from rasterio.errors import NotGeoreferencedWarning

    from planetref.simulate.render import render_ccd

    cfg = mini_config()
    sm = build_scene_model(cfg)
    cam = sm.strips[0].truth
    model = sm.radiance_model("target")
    out = []
    for p in (1, 2):
        path = tmp_path / f"p{p}.tif"
        render_ccd(
            cam,
            "ccd2",
            sm.dem,
            model,
            sm.enu,
            cfg.sensor,
            path,
            chunk_pixels=1024,
            noise_seed=np.random.SeedSequence(5),
            processes=p,
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.open(path) as ds:
                out.append(ds.read(1))
    assert out[0].std() > 0
    np.testing.assert_array_equal(out[0], out[1])


def test_difficulty_ladder_is_ordered_and_validated() -> None:
    from planetref.errors import InputError

    def sun_gap(cfg):  # type: ignore[no-untyped-def]
        t, r = cfg.photometry.target_sun, cfg.photometry.reference_sun
        return abs((r.azimuth_deg - t.azimuth_deg + 180.0) % 360.0 - 180.0)

    cfgs = [load_config("tiny", difficulty=d) for d in STRESS_LADDER]
    gaps = [sun_gap(c) for c in cfgs]
    assert gaps == sorted(gaps) and gaps[0] < gaps[-1]
    offs = [c.truth_mismatch.ccd_offset_px for c in cfgs]
    assert offs == sorted(offs)
    assert [c.reference.mosaic.n_sources for c in cfgs] == [1, 1, 3, 4]
    assert cfgs[2].surface_change.new_crater_density_per_km2 > 0
    assert cfgs[2].reference.mola.tracks and not cfgs[1].reference.mola.tracks
    # "moderate" is the preset as it is (only the name changes).
    plain = load_config("tiny").model_dump()
    moderate = cfgs[1].model_dump()
    assert moderate.pop("name") == "tiny-moderate" and plain.pop("name") == "tiny"
    assert moderate == plain
    with pytest.raises(
        InputError, match="valid difficulties: easy, moderate, realistic, hard, extreme"
    ):
        load_config("tiny", difficulty="brutal")


def _leaves(table: dict, prefix: str = "") -> list[str]:  # type: ignore[type-arg]
    out = []
    for k, v in table.items():
        if isinstance(v, dict):
            out += _leaves(v, f"{prefix}{k}.")
        else:
            out.append(f"{prefix}{k}")
    return out


def test_realistic_level_cites_a_source_for_every_value() -> None:
    """Every value the ``realistic`` level sets names the real statistic it reproduces."""
    table = load_difficulty_dict("realistic")
    sources = table["sources"]
    values = [k for k in _leaves(table) if not k.startswith(("sources.", "realism."))]
    assert len(values) >= 20
    # A value is cited by its own key or by the table it belongs to.
    uncited = [v for v in values if v not in sources and v.rpartition(".")[0] not in sources]
    assert uncited == []
    assert all(len(s) > 20 for s in sources.values())
    cfg = load_config("tiny", difficulty="realistic")
    assert cfg.sources == sources and len(cfg.realism.easier_than_real) >= 3
    # The stress levels and presets carry no sources (they are not measured).
    assert all(not load_config("tiny", difficulty=d).sources for d in STRESS_LADDER)
    assert "realistic" in DIFFICULTIES and "realistic" not in STRESS_LADDER


def test_realistic_sources_must_name_settings() -> None:
    from planetref.errors import InputError

    with pytest.raises(InputError, match=r"sources name no setting: photometry\.nope"):
        load_config("tiny", {"sources": {"photometry.nope": "a measurement"}})


def test_hiric_preset_is_hirics_focal_plane() -> None:
    cfg = load_config("hiric")
    cam = cfg.camera
    assert (cam.n_ccds, cam.n_samples) == (3, 6144) and cam.n_lines >= 16000
    assert 0 < cam.overlap_samples < 200 and cam.gsd_m == 0.5
    assert cfg.orbit.altitude_m == 265000.0 and cfg.render.processes == 2
    swath = (cam.n_ccds * cam.n_samples - (cam.n_ccds - 1) * cam.overlap_samples) * cam.gsd_m
    assert 8900.0 < swath < 9300.0


def test_realism_table_reads_back_from_the_written_config(tmp_path: Path) -> None:
    """What a report prints: every sourced setting with its value, read from the TOML."""
    import tomli_w

    from planetref.scene.realism import read_realism
    from planetref.simulate.provenance import realism_of

    cfg = load_config("tiny", difficulty="realistic")
    path = tmp_path / "config.toml"
    path.write_text(tomli_w.dumps(cfg.model_dump(mode="json", exclude_none=True)))
    back = read_realism(path)
    assert back == realism_of(cfg) and back.level == "realistic"
    by_key = {v.key: v for v in back.values}
    assert by_key["photometry.target_haze"].value == "0.45"
    assert by_key["reference.mosaic.offset_px"].value == "4"
    assert "Robbins" in by_key["reference.mosaic.offset_px"].source
    assert by_key["initial_errors.position_bias_m"].value == "(70, -50, 20)"
    assert len(back.easier_than_real) == len(cfg.realism.easier_than_real)
    # A stress level cites nothing.
    assert realism_of(load_config("tiny", difficulty="hard")).values == ()


def test_compare_report_prints_the_realistic_levels_sources(tmp_path: Path) -> None:
    """The report section of a simulated scene at ``realistic``: table and caveats."""
    from planetref.report.document import Document
    from planetref.report.georef import CompareContext, add_realism
    from planetref.simulate.provenance import realism_of

    realism = realism_of(load_config("tiny", difficulty="realistic"))
    ctx = CompareContext(
        scene="tiny-realistic",
        realism_level=realism.level,
        realism_sources=[tuple(v) for v in realism.values],
        easier_than_real=list(realism.easier_than_real),
    )
    doc = Document("t")
    add_realism(doc, ctx)
    md = doc.markdown(tmp_path)
    assert "Realism settings of the `realistic` level" in md
    assert "photometry.target_haze" in md and "Robbins et al. 2023" in md
    assert "relief displacement" in md
    # A scene without sources adds nothing.
    empty = Document("t")
    add_realism(empty, CompareContext(scene="x"))
    assert "Realism" not in empty.markdown(tmp_path)


def test_off_nadir_source_displaces_relief_like_an_offset(mini_config) -> None:  # type: ignore[no-untyped-def]
    """A source 20 deg off nadir looking east, on relief 10 m above its DEM, shows what a
    nadir source offset by -10 tan(20 deg) m in x shows (the relief-displacement law)."""
    import dataclasses
    import math

    from planetref.simulate.mosaic import draw_mosaic
    from planetref.simulate.reference import ortho_radiance

    cfg = mini_config()
    sm = build_scene_model(cfg)
    (src,), _ = draw_mosaic(
        cfg.reference.mosaic, cfg.photometry, sm.ortho_grid, np.random.default_rng(0)
    )
    model = sm.radiance_model("reference")
    shift = 10.0 * math.tan(math.radians(20.0))
    off_nadir = dataclasses.replace(src, emission_deg=20.0, look_azimuth_deg=90.0)
    shifted = dataclasses.replace(src, offset_m=(-shift, 0.0))
    out = []
    for s, relief in ((off_nadir, lambda x, y: np.full(np.shape(x), 10.0)), (shifted, None)):
        img = np.zeros(sm.ortho_grid.shape, dtype=np.float32)
        ortho_radiance(
            sm.ortho_grid, sm.ref, sm.local, model, cfg.reference, img, source=s, relief=relief
        )
        out.append(img)
    np.testing.assert_allclose(out[0], out[1], rtol=1e-6)
    # ... and the displacement is the analytic one (a feature moves away from the camera).
    dx, dy = off_nadir.displacement(np.zeros(2), np.zeros(2), np.array([10.0, -5.0]))
    np.testing.assert_allclose(dx, [-shift, 0.5 * shift])
    np.testing.assert_allclose(dy, 0.0, atol=1e-12)


def test_off_nadir_mosaic_is_seeded_and_leaves_nadir_mosaics_alone(
    mini_config, tmp_path: Path
) -> None:  # type: ignore[no-untyped-def]
    from planetref.simulate.mosaic import draw_mosaic

    mosaic = {"n_sources": 2, "offset_px": 1.0, "warp_px": 0.5}
    nadir = mini_config(reference={"mosaic": mosaic})
    tilted = mini_config(reference={"mosaic": {**mosaic, "emission_max_deg": 15.0}})
    sm = build_scene_model(nadir)
    a, _ = draw_mosaic(nadir.reference.mosaic, nadir.photometry, sm.ortho_grid, stream(0, "mosaic"))
    b, _ = draw_mosaic(
        tilted.reference.mosaic, tilted.photometry, sm.ortho_grid, stream(0, "mosaic")
    )
    # The emission angles are drawn after everything else: the rest is unchanged.
    for s, t in zip(a, b, strict=True):
        assert s.offset_m == t.offset_m and s.sun == t.sun and s.emission_deg == 0.0
        assert 0.0 < t.emission_deg <= 15.0 and t.look_azimuth_deg in (90.0, 270.0)
    simulate_scene(tilted, tmp_path / "x")
    simulate_scene(tilted, tmp_path / "y")
    one = (tmp_path / "x" / "reference" / "ortho.tif").read_bytes()
    assert one == (tmp_path / "y" / "reference" / "ortho.tif").read_bytes()
    simulate_scene(nadir, tmp_path / "z")
    assert one != (tmp_path / "z" / "reference" / "ortho.tif").read_bytes()
    ref = json.loads((tmp_path / "x" / "truth" / "reference.json").read_text())
    assert all(s["emission_deg"] > 0 for s in ref["mosaic"]["sources"])
