"""Orthorectification of CCD tiles onto the reference grid, and back to raw pixels."""

from __future__ import annotations

import numpy as np
import pytest

from planetref.camera.mapping import image_to_ref_pixel
from planetref.frontend.config import FrontendConfig
from planetref.frontend.orthorectify import downsample_tile, orthorectify
from planetref.frontend.tiles import plan_tiles, tile_footprint
from planetref.raster.image import CcdImage
from planetref.raster.ortho import ReferenceOrtho

# Fine stage on the reference grid (fine_upsample = 1): the numbers these tests assert
# were set there, and it keeps the default run fast; the default grid is tested in
# test_frontend_density.py.
CFG = FrontendConfig(tile_size_ref_px=96, uncertainty_m=150.0, coarse_factor=2, fine_upsample=1)


@pytest.fixture(scope="module")
def setup(scene):
    ref = ReferenceOrtho(scene.ortho_path)
    plan = plan_tiles(scene.init_cam, "ccd1", ref, scene.dem, CFG)
    img = CcdImage(scene.image_paths["ccd1"])
    yield scene, ref, plan, img
    img.close()
    ref.close()


def test_tile_plan_covers_image(setup):
    scene, _, plan, _ = setup
    assert 9.0 < plan.ratio < 10.5  # 0.5 m image over a ~4.85 m (geometric mean) grid
    n_lines, n_samples = scene.init_cam.image_size("ccd1")
    cover = np.zeros((n_lines, n_samples), bool)
    for t in plan.tiles:
        assert t.line0 >= 0 and t.sample0 >= 0
        assert t.line0 + t.n_lines <= n_lines and t.sample0 + t.n_samples <= n_samples
        cover[t.line0 : t.line0 + t.n_lines, t.sample0 : t.sample0 + t.n_samples] = True
    assert cover.all()
    assert len({t.tile_id for t in plan.tiles}) == len(plan.tiles)


def test_round_trip_to_raw(setup):
    scene, ref, plan, img = setup
    tile = plan.tiles[2]
    fp = tile_footprint(scene.init_cam, tile, ref, scene.dem)
    win = fp.window.padded(8)
    ortho = orthorectify(img, scene.init_cam, "ccd1", ref, scene.dem, win, lattice_step=8)
    rng = np.random.default_rng(3)
    line = tile.line0 + rng.uniform(0, tile.n_lines, 200)
    sample = tile.sample0 + rng.uniform(0, tile.n_samples, 200)
    col, row = image_to_ref_pixel(scene.init_cam, "ccd1", line, sample, ref, scene.dem)
    x, y = win.from_ref_pixel(col, row)
    back_l, back_s, ok = ortho.to_raw(x, y)
    assert ok.all()
    err = np.hypot(back_l - line, back_s - sample)
    assert err.max() < 0.05, err.max()
    print(f"ortho round trip: max {err.max():.2e} px")
    # The lattice interpolation that built the orthoimage is as good.
    il, is_ = ortho.raw_coords(x, y)
    lerr = np.hypot(il - line, is_ - sample)
    print(f"lattice interpolation: max {lerr.max():.2e} px")
    assert lerr.max() < 0.05
    assert ortho.prefilter == int(np.floor(0.5 * plan.ratio))


def test_true_camera_ortho_matches_reference(setup):
    """Through the TRUE camera the orthoimage lands on the reference: NCC peaks at 0."""
    scene, ref, plan, img = setup
    tile = plan.tiles[3]
    fp = tile_footprint(scene.true_cam, tile, ref, scene.dem)
    win = fp.window
    ortho = orthorectify(img, scene.true_cam, "ccd1", ref, scene.dem, win)
    assert ortho.valid.mean() > 0.6  # a CCD-edge tile: the image ends inside the window

    def ncc(dc, dr):
        r, rv = ref.read(win.shifted(dc, dr))
        m = ortho.valid & rv
        a, b = ortho.image[m] - ortho.image[m].mean(), r[m] - r[m].mean()
        return float(a @ b / np.sqrt((a @ a) * (b @ b)))

    centre = ncc(0, 0)
    assert centre > 0.95
    assert all(ncc(dc, dr) < centre for dc, dr in [(1, 0), (-1, 0), (0, 1), (0, -1)])


def test_validity_outside_image_and_nodata(scene, setup):
    _, ref, plan, _ = setup
    data = scene.images["ccd1"].copy()
    data[:, :300] = np.nan  # a no-data stripe along the CCD's left edge
    img = CcdImage(data)
    tile = plan.tiles[0]
    fp = tile_footprint(scene.init_cam, tile, ref, scene.dem)
    win = fp.window.padded(60)
    ortho = orthorectify(img, scene.init_cam, "ccd1", ref, scene.dem, win)
    gy, gx = np.mgrid[0 : win.height, 0 : win.width] + 0.5
    line, sample = ortho.raw_coords(gx, gy)
    outside = (line < 0) | (sample < 0) | (sample >= data.shape[1])
    assert outside.any() and not ortho.valid[outside].any()
    # No pixel whose raw position is deep in the no-data stripe is valid...
    assert not ortho.valid[(sample < 290) & ~outside].any()
    # ...and no-data never leaks into the values of valid pixels.
    assert np.isfinite(ortho.image).all()
    assert ortho.valid[(sample > 320) & ~outside & (line > 10)].mean() > 0.99
    # Bounds restrict the raw pixels used.
    o2 = orthorectify(img, scene.init_cam, "ccd1", ref, scene.dem, win, bounds=tile.bounds)
    l2, s2 = o2.raw_coords(gx, gy)
    assert not o2.valid[~tile.contains(l2, s2)].any()


def test_downsample_tile_mapping(setup):
    scene, ref, plan, img = setup
    tile = plan.tiles[1]
    ds = downsample_tile(img, tile, 10, scene.init_cam, ref, scene.dem)
    assert ds.image.shape == (-(-tile.n_lines // 10), -(-tile.n_samples // 10))
    line, sample, ok = ds.to_raw([0.5, 3.25], [0.5, 7.0])
    assert ok.all()
    np.testing.assert_allclose(line, [tile.line0 + 5.0, tile.line0 + 70.0])
    np.testing.assert_allclose(sample, [tile.sample0 + 5.0, tile.sample0 + 32.5])
    col, row = ds.predicted_ref_pixel([0.5], [0.5])
    c2, r2 = image_to_ref_pixel(scene.init_cam, "ccd1", line[:1], sample[:1], ref, scene.dem)
    np.testing.assert_allclose([col[0], row[0]], [c2[0], r2[0]])
    # The block image is the mean of the raw pixels of each block.
    raw, _ = img.read(tile.line0, tile.sample0, 10, 10)
    assert ds.image[0, 0] == pytest.approx(raw.mean(), rel=1e-5)


def test_cached_preparation_equals_direct(setup):
    """The per-reader caches (reference-grid lattice, raw block means) change nothing.

    Tiles of one CCD share lattice nodes and raw block means through the reader's caches;
    every stage image must equal the one built from the window's own lattice and a direct
    read (to the lattice interpolation's precision), on the coarse and the fine grid, with
    a fine_upsample grid too.
    """
    from planetref.frontend.grid import FineWindow
    from planetref.frontend.orthorectify import lattice_cache
    from planetref.raster.ortho import RefWindow

    scene, ref, plan, img = setup
    fresh = CcdImage(scene.image_paths["ccd1"])
    cache = lattice_cache(fresh, scene.init_cam, "ccd1", ref, scene.dem, 8)
    assert lattice_cache(fresh, scene.init_cam, "ccd1", ref, scene.dem, 8) is cache
    try:
        for tile in plan.tiles[:4]:
            fp = tile_footprint(scene.init_cam, tile, ref, scene.dem)
            c0, r0, c1, r1 = fp.window.bounds_px
            windows = [
                fp.window.padded(16),
                RefWindow.around(c0, r0, c1, r1, pad_px=40, factor=2),
                FineWindow(fp.window.padded(4), 2),
            ]
            for win in windows:
                direct = orthorectify(img, scene.init_cam, "ccd1", ref, scene.dem, win)
                cached = orthorectify(
                    fresh, scene.init_cam, "ccd1", ref, scene.dem, win, cache=cache
                )
                assert cached.prefilter == direct.prefilter
                assert cached.valid.sum() > 0.3 * cached.valid.size
                assert np.mean(cached.valid != direct.valid) < 1e-3
                both = cached.valid & direct.valid
                diff = np.abs(cached.image - direct.image)[both]
                # uint16 DN around 1e3: the two lattices differ by < 0.002 raw px
                assert diff.max() < 1e-3 * direct.image[both].std(), diff.max()
                x = np.array([3.5, win.width / 2, win.width - 4.0])
                y = np.array([2.5, win.height / 3, win.height - 3.0])
                la, sa = direct.raw_coords(x, y)
                lb, sb = cached.raw_coords(x, y)
                assert np.nanmax(np.abs(np.r_[la - lb, sa - sb])) < 0.01
    finally:
        fresh.close()


def test_block_mean_cache_equals_direct_read(setup):
    """Cached block means (bands over the whole width) equal a direct windowed read."""
    scene, _, _, _ = setup
    with (
        CcdImage(scene.image_paths["ccd1"]) as direct,
        CcdImage(scene.image_paths["ccd1"]) as cached,
    ):
        cached.BAND_ROWS = 8  # several bands, evicted and read again
        cached.MAX_CACHED_PIXELS = 3000
        n_lines, n_samples = direct.shape
        for k, (l0, s0, h, w) in [
            (4, (0, 0, 200, 160)),
            (4, (-8, 40, 120, 300)),
            (5, (n_lines - 95, n_samples - 105, 120, 130)),  # beyond the image end
            (3, (30, 60, 99, 33)),
            (4, (3, 5, 40, 40)),  # off the block grid: read directly
        ]:
            a, va = direct.read_block_mean(l0, s0, h, w, k)
            b, vb = cached.read_block_mean_cached(l0, s0, h, w, k)
            assert a.shape == b.shape and va.any()
            np.testing.assert_array_equal(va, vb)
            np.testing.assert_allclose(b[vb], a[va], rtol=1e-6)
        assert cached._band_pixels <= 3000 + n_samples


def test_raw_lines_decoded_once_for_all_factors(setup):
    """The coarse and fine decimated levels share one decode of the raw lines.

    Each raw line is read from the file once for both factors (while the decoded bands
    fit), the block means are bit for bit those of a direct read, and with room for one
    band only the cache stays within it and still gives the same means.
    """
    scene, _, _, _ = setup
    with (
        CcdImage(scene.image_paths["ccd1"]) as direct,
        CcdImage(scene.image_paths["ccd1"]) as cached,
    ):
        n_lines, n_samples = direct.shape
        calls = []
        raw = cached._raw

        def spy(r0, c0, r1, c1):
            calls.append((r0, c0, r1, c1))
            return raw(r0, c0, r1, c1)

        cached._raw = spy
        cached.RAW_BAND_LINES = 100  # several bands (whole blocks of the file)
        for k in (4, 9, 4):
            a, va = direct.read_block_mean(0, 0, n_lines, n_samples, k)
            b, vb = cached.read_block_mean_cached(0, 0, n_lines, n_samples, k)
            np.testing.assert_array_equal(va, vb)
            np.testing.assert_array_equal(a, b)
        assert sum(r1 - r0 for r0, _, r1, _ in calls) == n_lines
        assert len(calls) >= 2 and all(c0 == 0 and c1 == n_samples for _, c0, _, c1 in calls)
        cached.MAX_RAW_BYTES = 1  # one band at a time
        cached._bands.clear()
        cached._band_pixels = 0
        b, vb = cached.read_block_mean_cached(0, 0, n_lines, n_samples, 5)
        np.testing.assert_array_equal(b, direct.read_block_mean(0, 0, n_lines, n_samples, 5)[0])
        assert len(cached._raw_bands) == 1
        assert cached._raw_bytes == next(iter(cached._raw_bands.values())).nbytes


def test_lattice_nodes_do_not_depend_on_tile_order(setup):
    """A chunk's nodes do not depend on which chunks were projected with it.

    Workers fill their caches in whatever order their tiles come; schedulers must still
    give identical MCPs, so the nodes may not depend on that order.
    """
    from planetref.frontend.orthorectify import LatticeCache
    from planetref.raster.ortho import RefWindow

    scene, ref, plan, _ = setup
    fp = tile_footprint(scene.init_cam, plan.tiles[0], ref, scene.dem)
    c0, r0, _, _ = fp.window.bounds_px
    wins = [
        RefWindow(c0 - 20, r0 - 20, 140, 150, 1),
        RefWindow(c0 + 50, r0 + 60, 90, 70, 1),
        RefWindow(c0 - 60, r0 + 10, 60, 200, 2),
    ]
    one = LatticeCache(scene.init_cam, "ccd1", ref, scene.dem, 8, chunk=4)
    other = LatticeCache(scene.init_cam, "ccd1", ref, scene.dem, 8, chunk=4)
    a = [one.nodes(w) for w in wins]
    b = [other.nodes(w) for w in reversed(wins)][::-1]
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x[0], y[0])
        np.testing.assert_array_equal(x[1], y[1])
        for u, v in zip(x[2:], y[2:], strict=True):
            # numpy's vectorised arithmetic over arrays of other lengths: ~1e-12 px
            np.testing.assert_allclose(u, v, rtol=0, atol=1e-9)
            np.testing.assert_array_equal(np.isfinite(u), np.isfinite(v))
    assert np.isfinite(a[0][2]).mean() > 0.5
    # and the nodes are the exact projections of their reference positions
    lx, ly, line, sample = a[0]
    col, row = wins[0].to_ref_pixel(*np.meshgrid(lx, ly))
    mx, my = ref.pixel_to_map(col, row)
    from planetref.camera.mapping import map_to_ground, project_to_image

    xyz, *_ = map_to_ground(ref, scene.dem, mx.ravel(), my.ravel())
    el, es = project_to_image(scene.init_cam, "ccd1", xyz)
    ok = np.isfinite(line.ravel())
    np.testing.assert_allclose(line.ravel()[ok], el[ok], atol=1e-6)
    np.testing.assert_allclose(sample.ravel()[ok], es[ok], atol=1e-6)


def test_coarse_lattice_is_every_other_fine_node(setup):
    """A coarse stage takes every ``stride``-th node of the fine stages' cache.

    The nodes are the same exact projections as those of a cache of the coarse spacing
    (to the projection's convergence, ~1e-10 px), so one cache per CCD serves both stages.
    """
    from planetref.frontend.orthorectify import LatticeCache
    from planetref.raster.ortho import RefWindow

    scene, ref, plan, _ = setup
    fp = tile_footprint(scene.init_cam, plan.tiles[0], ref, scene.dem)
    c0, r0, c1, r1 = fp.window.bounds_px
    win = RefWindow.around(c0, r0, c1, r1, pad_px=13, factor=2)
    fine = LatticeCache(scene.init_cam, "ccd1", ref, scene.dem, 8, chunk=4)
    coarse = LatticeCache(scene.init_cam, "ccd1", ref, scene.dem, 16, chunk=4)
    a, b = fine.nodes(win, stride=2), coarse.nodes(win)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert a[2].shape == b[2].shape and np.isfinite(a[2]).mean() > 0.5
    for u, v in zip(a[2:], b[2:], strict=True):
        np.testing.assert_array_equal(np.isfinite(u), np.isfinite(v))
        np.testing.assert_allclose(u, v, rtol=0, atol=1e-8)


def test_raw_coords_grid_equals_pointwise(setup):
    """The separable grid evaluation gives the pointwise (scipy) values, NaN for NaN.

    Interpolating the lattice rows first and then the rows changes only the order of the
    additions (~1e-13 px); inside the lattice and off its nodes (pixel centres never fall
    on a node), a value is NaN exactly where scipy's is. The columns-first evaluation
    through :func:`~planetref.geometry.lattice.bilinear_lattice` (transposed) is bit for
    bit the front end's former one (every node with a weight entering, even 0).
    """
    from scipy import ndimage

    from planetref.geometry.lattice import bilinear_lattice, lattice_cell

    scene, ref, plan, img = setup
    fp = tile_footprint(scene.init_cam, plan.tiles[0], ref, scene.dem)
    o = orthorectify(img, scene.init_cam, "ccd1", ref, scene.dem, fp.window.padded(8))
    xs = np.arange(o.window.width, dtype=np.float64) + 0.5
    ys = np.arange(o.window.height, dtype=np.float64) + 0.5
    gl, gs = o.raw_coords_grid(xs, ys)
    pl, ps = o.raw_coords(*np.meshgrid(xs, ys))
    assert gl.shape == (len(ys), len(xs)) and np.isfinite(gl).mean() > 0.5
    for g, p in ((gl, pl), (gs, ps)):
        np.testing.assert_array_equal(np.isnan(g), np.isnan(p))
        np.testing.assert_allclose(g, p, rtol=0, atol=1e-9)
    grid = np.random.default_rng(3).uniform(0.0, 1000.0, (6, 5))
    grid[1, 1] = grid[4, 3] = grid[5, 0] = np.nan
    fy, fx = np.linspace(0.05, 4.95, 33), np.linspace(0.03, 3.97, 27)
    iy, ty = lattice_cell(fy, 6)
    ix, tx = lattice_cell(fx, 5)
    got = bilinear_lattice(grid.T, ix, tx, iy, ty).T
    coords = np.vstack([np.repeat(fy, len(fx)), np.tile(fx, len(fy))])
    want = ndimage.map_coordinates(grid, coords, order=1, mode="nearest", prefilter=False)
    np.testing.assert_array_equal(np.isnan(got.ravel()), np.isnan(want))
    assert 0 < np.isnan(want).sum() < want.size
    np.testing.assert_allclose(got.ravel(), want, rtol=0, atol=1e-9)
    # The former front-end formula (columns first, clamped nodes): the same bits.
    x0, y0 = np.floor(fx).astype(int), np.floor(fy).astype(int)
    rows = grid[:, x0] * (1.0 - (fx - x0)) + grid[:, x0 + 1] * (fx - x0)
    former = rows[y0] * (1.0 - (fy - y0))[:, None] + rows[y0 + 1] * (fy - y0)[:, None]
    np.testing.assert_array_equal(got, former)


def test_guided_lattice_equals_probed_search(setup):
    """The line guide changes no node: the same valid nodes, the same lines and samples.

    Every node of a region reaching past both strip ends and both CCD sides is projected
    from the guide's starting line (compiled) and, as the reference, from affine fits to
    bracket-searched probes (the numpy line search); both converge to the camera's root.
    """
    from planetref.frontend.orthorectify import LatticeCache

    scene, ref, _, _ = setup
    cache = LatticeCache(scene.init_cam, "ccd1", ref, scene.dem, 8, chunk=4)
    guide = cache._line_guide()
    assert guide is not None
    rows, cols = ref.shape
    n = cache.chunk * cache.step
    todo = [(i, j) for i in range(-1, rows // n + 2) for j in range(-1, cols // n + 2)]
    line, sample = cache._fill_guided(todo, guide)
    ref_line, ref_sample = cache._fill_probed(todo)
    ok = np.isfinite(line)
    np.testing.assert_array_equal(ok, np.isfinite(ref_line))
    assert 0.2 < ok.mean() < 0.95  # the region reaches well beyond the image
    n_lines, n_samples = scene.init_cam.image_size("ccd1")
    assert line[ok].min() < 0 < n_lines < line[ok].max()
    assert sample[ok].min() < 0 < n_samples < sample[ok].max()
    np.testing.assert_allclose(line[ok], ref_line[ok], rtol=0, atol=1e-8)
    np.testing.assert_allclose(sample[ok], ref_sample[ok], rtol=0, atol=1e-8)
    # A guide's start is within a few lines of the root inside its table.
    col, row = cache._chunk_nodes(todo)
    start, inside = guide(col, row)
    assert np.abs(start - line)[inside & ok].max() < 5.0


def test_compiled_block_sampling_equals_scipy():
    """The compiled bilinear sampling gives scipy's float32 values and valid fractions."""
    from planetref.frontend.resample import bilinear_blocks, bilinear_blocks_numpy
    from planetref.runtime.optional import optional_module

    if optional_module("planetref.frontend._numba_resample", "compiled resampling") is None:
        pytest.skip("numba is not available: only the scipy way runs")
    rng = np.random.default_rng(5)
    block = rng.uniform(0.0, 4000.0, (40, 37)).astype(np.float32)
    valid = rng.uniform(size=block.shape) > 0.05
    y, x = np.mgrid[0:90, 0:80].astype(np.float64)
    u = 0.47 * y + 0.03 * x - 2.2 + rng.normal(0.0, 1e-3, y.shape)
    v = 0.49 * x - 0.02 * y - 1.3
    # NaN, infinity, exactly on the last centres, just beyond them, on the first ones
    u[1, 1], u[2, 2], v[3, 3] = np.nan, np.inf, np.nan
    u[4, 4], v[5, 5], u[6, 6], v[7, 7], u[8, 8] = 39.0, 36.0, 39.0 + 1e-9, -1e-12, 0.0
    got, got_frac = bilinear_blocks(block, valid, u, v)
    want, want_frac = bilinear_blocks_numpy(block, valid, u, v)
    assert got.dtype == want.dtype == np.float32 and got.shape == u.shape
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(got_frac, want_frac)
    assert 0.2 < np.mean(got_frac > 1 - 1e-4) < 0.9
