"""TDI camera radiometry (compression blocks, saturation) and the CTX/MOLA-like reference
(seam brightness steps, DEM error between altimetry tracks): each effect is measured."""

from __future__ import annotations

import io
import itertools
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter, map_coordinates

from planetref.simulate.scene import build_scene_model
from planetref.simulate.sensor import block_dct_compress, jpeg_table


def _smooth_image(seed: int, shape: tuple[int, int] = (128, 160)) -> np.ndarray:
    """An 8-bit image of smooth texture plus fine noise (what the camera would see)."""
    rng = np.random.default_rng(seed)
    smooth = gaussian_filter(rng.standard_normal(shape), 3.0)
    img = 128.0 + 40.0 * smooth / smooth.std() + 3.0 * rng.standard_normal(shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def test_jpeg_table_follows_the_ijg_quality_rule() -> None:
    np.testing.assert_array_equal(jpeg_table(50, 8)[0], [16, 11, 10, 16, 24, 40, 51, 61])
    assert np.all(jpeg_table(100, 8) == 1.0)
    # q = 75 halves the table (scale 50 %), q = 25 doubles it (200 %).
    assert jpeg_table(75, 8)[0, 0] == 8.0 and jpeg_table(25, 8)[0, 0] == 32.0
    np.testing.assert_allclose(jpeg_table(50, 16), jpeg_table(50, 8) * 65535 / 255)


def test_block_dct_matches_libjpeg() -> None:
    """Our round trip and Pillow's (libjpeg, integer DCT) decode to nearly the same DN."""
    from PIL import Image

    img = _smooth_image(0)
    for q in (50, 85):
        ours = block_dct_compress(img, q, 8).astype(float)
        buf = io.BytesIO()
        Image.fromarray(img).save(buf, format="JPEG", quality=q)
        theirs = np.asarray(Image.open(buf), dtype=float)
        loss, loss_lib = np.abs(ours - img).mean(), np.abs(theirs - img).mean()
        assert loss > 1.0  # the compression is lossy (2.1-2.8 DN)
        assert abs(loss / loss_lib - 1.0) < 0.02
        diff = np.abs(ours - theirs)
        # libjpeg's integer DCT rounds a few coefficients the other way (a whole step).
        assert diff.mean() < 0.25 and (diff == 0).mean() > 0.8, (q, diff.mean())
        assert np.percentile(diff, 99) <= 3.0


def test_compression_blocks_appear_at_8_pixel_period() -> None:
    """The mean jump between neighbouring samples is a comb at 1/8 cycle per pixel: most of
    its spectrum's power is at 1/8, 2/8, 3/8 and 4/8 cycle per pixel."""
    img = _smooth_image(1, (512, 256))

    def comb_share(a: np.ndarray) -> float:
        d = np.abs(np.diff(a.astype(float), axis=1)).mean(axis=0)[:248]  # 31 periods of 8
        p = np.abs(np.fft.rfft(d - d.mean())) ** 2
        return float(p[[31, 62, 93, 124]].sum() / p[1:].sum())

    shares = [comb_share(block_dct_compress(img, q, 8)) for q in (30, 50, 75, 85)]
    assert comb_share(img) < 0.05  # 4 of 124 frequencies: no comb before coding
    assert shares[0] > 0.8 and shares[-1] > 0.25
    assert shares == sorted(shares, reverse=True)  # stronger with coarser quantisation
    # The jumps are larger across block edges (sample 8k-1 -> 8k) than inside blocks.
    out = block_dct_compress(img, 30, 8).astype(float)
    d = np.abs(np.diff(out, axis=1)).mean(axis=0)
    edge = d[7::8].mean()
    inside = np.delete(d, np.s_[7::8]).mean()
    assert edge > 1.3 * inside


def test_compression_keeps_16_bit_images_and_block_alignment() -> None:
    img = (_smooth_image(2, (37, 45)).astype(np.uint16) * 257).astype(np.uint16)
    out = block_dct_compress(img, 90, 16)
    assert out.dtype == np.uint16 and out.shape == img.shape
    rel = np.abs(out.astype(float) - img) / 257.0
    assert 0.05 < rel.mean() < 2.0
    # Blocks are aligned on the first line: coding the top 16 lines alone gives the same.
    np.testing.assert_array_equal(block_dct_compress(img[:16], 90, 16), out[:16])


def _render(mini_config, tmp_path: Path, **sensor):  # type: ignore[no-untyped-def]
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning

    from planetref.simulate.render import render_ccd

    cfg = mini_config(sensor=sensor)
    sm = build_scene_model(cfg)
    path = tmp_path / f"img{len(list(tmp_path.iterdir()))}.tif"
    stats = render_ccd(
        sm.strips[0].truth,
        "ccd2",
        sm.dem,
        sm.radiance_model("target"),
        sm.enu,
        cfg.sensor,
        path,
        chunk_pixels=1000,
        noise_seed=np.random.SeedSequence(5),
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(path) as ds:
            return stats, ds.read(1)


def test_saturation_fraction_is_as_configured(mini_config, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    plain, img0 = _render(mini_config, tmp_path)
    assert plain["saturated_fraction"] == 0.0 and "mean_signal_e" not in plain
    for f in (0.02, 0.1):
        stats, img = _render(mini_config, tmp_path, saturation_fraction=f)
        assert 0.6 * f < stats["saturated_fraction"] < 1.4 * f, stats
        assert stats["mean_signal_e"] > 25_000.0  # the exposure went up to clip the top
        assert np.count_nonzero(img == 65535) / img.size == stats["saturated_fraction"]
    # Rendering without the new settings is what it was (blocks, noise and all).
    _, img1 = _render(mini_config, tmp_path, compression_quality=0, saturation_fraction=0.0)
    np.testing.assert_array_equal(img0, img1)


def test_compressed_ccd_image_is_block_coded(mini_config, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    _, plain = _render(mini_config, tmp_path)
    _, coded = _render(mini_config, tmp_path, compression_quality=60)
    # The same noise, then coded: re-coding the coded image changes it little (the
    # blocks are on the image's grid even though it was rendered in blocks of lines).
    assert np.abs(coded.astype(float) - plain).mean() > 10.0
    recoded = block_dct_compress(coded, 60, 16)
    assert (
        np.abs(recoded.astype(float) - coded).mean()
        < 0.2 * np.abs(coded.astype(float) - plain).mean()
    )


def test_seams_step_brightness_by_the_sources_gain_and_bias(mini_config) -> None:  # type: ignore[no-untyped-def]
    """On level ground of one albedo, each side of a seam is ``gain * r + bias``."""
    import dataclasses

    from planetref.simulate.config import SunConfig
    from planetref.simulate.mosaic import MosaicSource, draw_mosaic
    from planetref.simulate.photometry import RadianceModel, ShadingFields
    from planetref.simulate.reference import ortho_radiance

    cfg = mini_config(
        photometry={"reference_haze": 0.0},
        reference={
            "mosaic": {"n_sources": 2, "gain_spread": 0.05, "bias_spread": 0.03},
        },
    )
    sm = build_scene_model(cfg)
    grid = sm.grid
    flat = np.zeros(grid.shape, np.float32)
    albedo = np.full(grid.shape, 0.25, np.float32)
    fields = ShadingFields(grid, flat, albedo, np.zeros(grid.shape), flat)
    sun = SunConfig(azimuth_deg=250.0, elevation_deg=34.0)
    model = RadianceModel(fields, sm.tiles, sun, cfg.photometry, cfg.albedo, 0.0)
    sources, seams = draw_mosaic(
        cfg.reference.mosaic, cfg.photometry, sm.ortho_grid, np.random.default_rng(4)
    )
    og = sm.ortho_grid
    img = np.zeros(og.shape, np.float32)
    for s in sources:
        s = dataclasses.replace(s, sun=sun)  # one sun: only gain and bias differ
        ortho_radiance(og, sm.ref, sm.local, model, cfg.reference, img, source=s, seams=seams)
    # The plain reference (gain 1, no bias) gives r.
    plain = np.zeros(og.shape, np.float32)
    one = MosaicSource(0, sun, 0.0, 1.0, (0.0, 0.0), np.zeros((0, 5)))
    ortho_radiance(og, sm.ref, sm.local, model, cfg.reference, plain, source=one)
    xc = og.x0 + (np.arange(og.cols) + 0.5) * og.res
    yc = og.y0 - (np.arange(og.rows) + 0.5) * og.res
    lab = seams.label(*np.meshgrid(xc, yc))
    assert set(np.unique(lab)) == {0, 1}
    r = float(np.median(plain))
    g0, g1 = sources[0].gain, sources[1].gain
    b0, b1 = sources[0].bias, sources[1].bias
    assert b0 != 0.0 and b1 != 0.0
    expected = (g1 * r + b1) - (g0 * r + b0)
    step = float(np.median(img[lab == 1]) - np.median(img[lab == 0]))
    assert abs(expected) > 0.005  # the test means something
    assert abs(step - expected) < 1e-4 * max(1.0, r), (step, expected)
    # Pixel by pixel, each source is the plain image times its gain plus its bias.
    for k, s in enumerate(sources):
        np.testing.assert_allclose(img[lab == k], s.gain * plain[lab == k] + s.bias, atol=2e-6)


def test_source_biases_are_drawn_with_the_configured_spread(mini_config) -> None:  # type: ignore[no-untyped-def]
    from planetref.simulate.mosaic import draw_mosaic

    base = {"n_sources": 12, "offset_px": 1.0, "gain_spread": 0.03}
    with_bias = mini_config(reference={"mosaic": {**base, "bias_spread": 0.02}})
    without = mini_config(reference={"mosaic": base})
    sm = build_scene_model(without)
    biases = []
    for seed in range(30):
        a, _ = draw_mosaic(
            without.reference.mosaic, without.photometry, sm.ortho_grid, np.random.default_rng(seed)
        )
        b, _ = draw_mosaic(
            with_bias.reference.mosaic,
            with_bias.photometry,
            sm.ortho_grid,
            np.random.default_rng(seed),
        )
        # Drawn last: everything else is as without biases.
        assert [(s.gain, s.offset_m, s.sun) for s in a] == [(s.gain, s.offset_m, s.sun) for s in b]
        assert all(s.bias == 0.0 for s in a)
        biases += [s.bias for s in b]
    assert 0.017 < float(np.std(biases)) < 0.023


def _tracks_cfg(**mola):  # type: ignore[no-untyped-def]
    from planetref.simulate.config import ReferenceConfig

    base = {
        "tracks": True,
        "track_spacing_m": 1500.0,
        "shot_spacing_m": 100.0,
        "track_azimuth_deg": 0.0,
        "track_offset_m": 0.0,
        "track_tilt_m": 0.0,
    }
    return ReferenceConfig(dem_noise_m=0.0, mola={**base, **mola})


def test_dem_error_between_tracks_is_the_interpolation_law() -> None:
    """Ground curved across the tracks: error ``k u (s - u) / 2`` at ``u`` from a track."""
    from planetref.simulate.reference import gridded_tracks

    kappa = 2e-5  # 1/m: a 2 km-wide valley 10 m deep
    xx, yy = np.meshgrid(np.arange(0.0, 6000.0, 25.0), np.arange(0.0, 4000.0, 100.0))
    rec: dict = {}
    h = gridded_tracks(
        xx, yy, lambda x, y: 0.5 * kappa * x**2, _tracks_cfg(), np.random.default_rng(2), rec
    )
    err = h - 0.5 * kappa * xx**2
    across = np.sort(np.array(rec["tracks"]["across_m"]))
    k = np.searchsorted(across, xx[0]) - 1
    left, right = across[k], across[k + 1]
    expected = 0.5 * kappa * (xx[0] - left) * (right - xx[0])
    np.testing.assert_allclose(err[5:-5], np.broadcast_to(expected, err[5:-5].shape), atol=1e-6)
    # So the error grows with the distance to the nearest track: 0 on it, ~k s^2/8 midway.
    dist = np.minimum(xx[0] - left, right - xx[0])
    near, far = np.abs(err[5, dist < 100.0]), np.abs(err[5, dist > 500.0])
    assert near.max() < 0.7 * far.min()
    assert err.max() > 2.0


def test_track_shift_moves_heights_by_slope_times_shift() -> None:
    from planetref.simulate.reference import gridded_tracks

    slope = 0.1
    xx, yy = np.meshgrid(np.arange(0.0, 6000.0, 25.0), np.arange(0.0, 4000.0, 100.0))
    rec: dict = {}
    cfg = _tracks_cfg(track_shift_m=80.0)
    h = gridded_tracks(xx, yy, lambda x, y: slope * x, cfg, np.random.default_rng(2), rec)
    tr = rec["tracks"]
    shifts = np.array(tr["shift_along_across_m"])
    assert 40.0 < np.std(shifts) < 120.0
    for x, (_, da) in zip(tr["across_m"], shifts, strict=True):
        col = int(np.argmin(np.abs(xx[0] - x)))
        if abs(xx[0, col] - x) < 1.0 and 0 < col < xx.shape[1] - 1:
            np.testing.assert_allclose(h[5:-5, col] - slope * x, slope * da, atol=0.1)
    # Without the shift, the draws are as they were (the shifts are drawn only when set).
    a = gridded_tracks(xx, yy, lambda x, y: slope * x, _tracks_cfg(), np.random.default_rng(2))
    np.testing.assert_allclose(a, slope * xx, atol=1e-6)


def test_dem_error_grows_with_distance_from_tracks_on_rough_ground() -> None:
    """On random ground with km-scale relief, the gridded DEM's RMS error rises from the
    tracks' own error (offsets of 1 m) to several metres midway between tracks."""
    from planetref.simulate.reference import gridded_tracks

    rng = np.random.default_rng(0)
    field = gaussian_filter(rng.standard_normal((400, 400)), 12.0)
    field *= 40.0 / field.std()  # 40 m RMS relief, correlated over ~300 m (25 m cells)

    def truth(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return map_coordinates(field, [y / 25.0, x / 25.0], order=1, mode="nearest")

    xx, yy = np.meshgrid(np.arange(1000.0, 9000.0, 25.0), np.arange(1000.0, 9000.0, 50.0))
    rec: dict = {}
    cfg = _tracks_cfg(track_offset_m=1.0, shot_spacing_m=330.0)
    h = gridded_tracks(xx, yy, truth, cfg, np.random.default_rng(5), rec)
    err = h - truth(xx.ravel(), yy.ravel()).reshape(xx.shape)
    across = np.sort(np.array(rec["tracks"]["across_m"]))
    dist = np.min(np.abs(xx[..., None] - across), axis=-1)
    bins = [0, 100, 300, 500, 800]
    rms = [
        float(np.sqrt(np.mean(err[(dist >= a) & (dist < b)] ** 2)))
        for a, b in itertools.pairwise(bins)
    ]
    assert rms == sorted(rms), rms
    assert rms[-1] > 2.0 * rms[0], rms


@pytest.mark.parametrize("level", ["moderate", "hard"])
def test_new_settings_are_off_outside_realistic(level: str) -> None:
    from planetref.simulate.config import load_config

    cfg = load_config("tiny", difficulty=level)
    assert cfg.sensor.compression_quality == 0 and cfg.sensor.saturation_fraction == 0.0
    assert cfg.reference.mosaic.bias_spread == 0.0 and cfg.reference.mola.track_shift_m == 0.0


def test_realistic_level_turns_them_on_with_sources() -> None:
    from planetref.simulate.config import load_config

    cfg = load_config("tiny", difficulty="realistic")
    assert cfg.sensor.compression_quality > 0 and cfg.reference.mosaic.bias_spread > 0
    assert cfg.reference.mola.track_shift_m > 0
    # Per-source misregistration of tens of metres (RMS radial), not the controlled 7 m.
    mosaic = cfg.reference.mosaic
    assert np.hypot(mosaic.offset_px, mosaic.offset_px) * cfg.reference.ortho_gsd_m > 20.0
    for key in (
        "sensor.compression_quality",
        "sensor.saturation_fraction",
        "reference.mosaic.bias_spread",
        "reference.mola.track_shift_m",
    ):
        assert len(cfg.sources[key]) > 100, key
