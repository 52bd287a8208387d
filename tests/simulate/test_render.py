from __future__ import annotations

import numpy as np

from planetref.simulate.render import render_radiance
from planetref.simulate.scene import build_scene_model


def test_each_pixel_shows_the_surface_along_its_own_ray(mini_config) -> None:  # type: ignore[no-untyped-def]
    """Render with one sub-sample per pixel and re-evaluate the radiance independently at
    the ground point that the true camera's ``image_to_ground`` gives for the pixel centre
    (the lead's ray caster on the truth DEM)."""
    cfg = mini_config(sensor={"supersample": 1})
    sm = build_scene_model(cfg)
    model = sm.radiance_model("target")
    cam = sm.strips[0].truth
    rng = np.random.default_rng(5)
    for ccd in cam.ccd_names:
        img = render_radiance(cam, ccd, sm.dem, model, sm.enu, 40, 56, supersample=1)
        _, n_samples = cam.image_size(ccd)
        lines = rng.integers(40, 56, 40)
        samples = rng.integers(0, n_samples, 40)
        xyz = cam.image_to_ground(lines + 0.5, samples + 0.5, sm.dem, ccd=ccd)
        x, y, _ = sm.dem.xyz_to_map(xyz)
        _, d = cam.look_rays(lines + 0.5, samples + 0.5, ccd=ccd)
        view = -d @ sm.enu.T
        expected = model.evaluate(x, y, view)
        got = img[lines - 40, samples]
        np.testing.assert_allclose(got, expected, rtol=2e-3)


def test_supersampling_integrates_the_footprint(mini_config) -> None:  # type: ignore[no-untyped-def]
    cfg = mini_config()
    sm = build_scene_model(cfg)
    model = sm.radiance_model("target")
    cam = sm.strips[0].truth
    one = render_radiance(cam, "ccd1", sm.dem, model, sm.enu, 0, 32, supersample=1)
    four = render_radiance(cam, "ccd1", sm.dem, model, sm.enu, 0, 32, supersample=4)
    # Same mean brightness, less pixel-to-pixel variance (the box filter).
    assert abs(one.mean() - four.mean()) < 0.02 * one.mean()
    assert np.diff(four, axis=1).std() < np.diff(one, axis=1).std()


def test_ortho_georeference_puts_features_at_their_true_place(mini_config) -> None:  # type: ignore[no-untyped-def]
    """A bright 6 m square on a dark surface lands where the ortho's geotransform says."""
    from planetref.simulate.photometry import RadianceModel, ShadingFields
    from planetref.simulate.reference import render_ortho

    cfg = mini_config(
        reference={"ortho_sensor": {"read_noise_e": 0.0, "bit_depth": 16, "full_well_e": 60000.0}}
    )
    sm = build_scene_model(cfg)
    grid = sm.grid
    flat = np.zeros(grid.shape, np.float32)
    albedo = np.full(grid.shape, 0.02, np.float32)
    r0, c0 = grid.rows // 2 + 7, grid.cols // 2 - 11
    albedo[r0 : r0 + 3, c0 : c0 + 3] = 0.9  # 3 x 3 cells of 2 m
    fields = ShadingFields(grid, flat, albedo, np.zeros(grid.shape), flat)
    phot = cfg.photometry
    model = RadianceModel(fields, sm.tiles, phot.reference_sun, phot, cfg.albedo, 0.0)
    ortho = render_ortho(
        sm.ortho_grid, sm.ref, sm.local, model, cfg.reference, np.random.default_rng(0)
    ).astype(float)
    # Expected position: the square's centre, through lon/lat, in the reference CRS.
    x = grid.x0 + (c0 + 1.5) * grid.res
    y = grid.y0 - (r0 + 1.5) * grid.res
    lon, lat = sm.local.map_to_lonlat(np.array([x]), np.array([y]))
    ex, ey = sm.ref.lonlat_to_map(lon, lat)
    og = sm.ortho_grid
    # Brightness-weighted centroid of the spot in the ortho.
    win = ortho - np.median(ortho)
    rows, cols = np.nonzero(win > 0.05 * win.max())
    w = win[rows, cols]
    cx = og.x0 + (np.average(cols, weights=w) + 0.5) * og.res
    cy = og.y0 - (np.average(rows, weights=w) + 0.5) * og.res
    assert abs(cx - ex[0]) < 0.5 and abs(cy - ey[0]) < 0.5


def test_column_gain_stripes_the_columns_and_leaves_the_noise(mini_config, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """``sensor.column_gain_rms``: each DN is the unstriped DN times its column's gain.

    The noise draws are the same with and without (the gains come from a child seed
    spawned after the blocks'), so the ratio of the two images is, per column, the gain:
    constant down the column (to quantisation and the noise's sqrt(gain) change), with
    the configured RMS across columns.
    """
    import rasterio

    from planetref.simulate.render import render_ccd
    from planetref.simulate.streams import seed_sequence

    sm = build_scene_model(mini_config())
    model = sm.radiance_model("target")
    cam = sm.strips[0].truth
    images = []
    for rms in (0.0, 0.02):
        sensor = sm.cfg.sensor.model_copy(update={"column_gain_rms": rms})
        path = tmp_path / f"ccd1_{rms}.tif"
        render_ccd(
            cam,
            "ccd1",
            sm.dem,
            model,
            sm.enu,
            sensor,
            path,
            chunk_pixels=4096,
            noise_seed=seed_sequence(3, "ccd_noise", 0, 0),
        )
        with rasterio.open(path) as ds:
            images.append(ds.read(1).astype(np.float64))
    plain, striped = images
    ratio = striped / plain
    gain = np.median(ratio, axis=0)
    # Constant down each column to ~1e-3 (noise of sqrt(gain) and DN rounding) ...
    assert np.percentile(np.abs(ratio - gain[None, :]), 99) < 2e-3
    # ... and the gains' spread is the configured 2 % (64 columns: +-30 %).
    assert 0.013 < gain.std() < 0.027
    assert abs(gain.mean() - 1.0) < 0.01
