"""Ray/DEM intersection speed and precision on a front-end-sized batch.

A nadir line-scan camera (2 CCDs of 2,000 samples, 20,000 lines) over a 50 m DEM of
rough terrain; 262,144 rays (a 512 x 512 lattice of image points, the size of a front-end
orthorectification batch) and a second batch looking 25 degrees off nadir, which the
grid's fixed-point guess declines (slope x tan(angle) too large) so the rays are marched.
Prints seconds per batch (best of N) and the largest height residual |h_ray - DEM| of the
hits (metres). Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_terrain.py [--json-out FILE]``
(``--json-out`` also writes the figures, the machine, date and command as JSON for the
documentation's benchmarks page).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy import ndimage

from planetref.camera.orbit import OrbitGeometry, ccd_row, orbit_camera
from planetref.geometry.geodesy import MARS_IAU2015_SPHERE, xyz_to_lonlat
from planetref.raster.dem import GridTerrain

LAT, LON = 20.0, 74.0
R = MARS_IAU2015_SPHERE.semi_major_m


def scene(holes: int = 0) -> tuple[object, GridTerrain]:
    ccds = ccd_row(2, 2000, 20000, 0.010, overlap_px=48)
    cam, _ = orbit_camera(OrbitGeometry(LAT, LON, 30.0), focal_length_mm=5300.0, ccds=ccds)
    res = 50.0
    n = 400
    rng = np.random.default_rng(1)
    h = ndimage.gaussian_filter(rng.normal(size=(n, n)), 6) * 4000.0
    x0 = np.radians(LON) * R - n / 2 * res
    y0 = np.radians(LAT) * R + n / 2 * res
    if holes:
        idx = rng.integers(50, n - 50, size=(holes, 2))
        h[idx[:, 0], idx[:, 1]] = np.nan
    dem = GridTerrain(h.astype(np.float32), (x0, res, 0, y0, 0, -res), "IAU_2015:49910")
    return cam, dem


def rays(cam, off_nadir_deg: float = 0.0):
    n_lines, n_samples = cam.image_size("ccd1")
    gl, gs = np.meshgrid(
        np.linspace(0.5, n_lines - 0.5, 512), np.linspace(0.5, n_samples - 0.5, 512), indexing="ij"
    )
    o, d = cam.look_rays(gl.ravel(), gs.ravel(), ccd="ccd1")
    if off_nadir_deg:
        # Same footprint seen obliquely: move the origins east, aim at the nadir points
        # on the mean surface.
        p = o + (np.linalg.norm(o, axis=1) - R)[:, None] * d / np.linalg.norm(d, axis=1)[:, None]
        east = np.array([-np.sin(np.radians(LON)), np.cos(np.radians(LON)), 0.0])
        dist = np.linalg.norm(o - p, axis=1)[:, None]
        o = o + east * dist * np.tan(np.radians(off_nadir_deg))
        d = p - o
    return o, d


def bench(dem, o, d, repeat=3):
    best = best_cpu = np.inf
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        hits = dem.intersect_rays(o, d)
        best = min(best, time.perf_counter() - t)
        best_cpu = min(best_cpu, time.process_time() - c)
    lon, lat, h = xyz_to_lonlat(hits.xyz, dem.ellipsoid)
    ok = np.isfinite(h)
    res = np.abs(h[ok] - dem.height(lon[ok], lat[ok]))
    n_hit = int(np.isfinite(hits.height).sum())
    return best, best_cpu, hits, float(np.max(res, initial=0.0)), n_hit


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json-out", help="also write the figures as JSON to this file")
    args = ap.parse_args()
    from machine import describe, result_record, write_result

    machine = describe()  # the load before this run's own work
    cam, dem = scene()
    figures: list[dict[str, object]] = []
    for name, off in (("nadir", 0.0), ("25deg", 25.0)):
        o, d = rays(cam, off)
        t, cpu, hits, res, n_hit = bench(dem, o, d)
        np.save(f"/tmp/bench_terrain_{name}.npy", hits.xyz)
        print(
            f"{name}: {len(o)} rays, {t:.3f} s ({cpu:.3f} CPU-s), hits {n_hit}, "
            f"max |h - DEM| {res:.2e} m"
        )
        figures += [
            {
                "name": f"{name}: CPU time per batch",
                "value": round(cpu, 4),
                "unit": "CPU-s",
                "note": f"{len(o)} rays, best of 3",
            },
            {
                "name": f"{name}: wall time per batch",
                "value": round(t, 4),
                "unit": "s",
                "note": "best of 3",
            },
            {"name": f"{name}: rays that hit", "value": n_hit, "unit": "rays"},
            {
                "name": f"{name}: max height residual of the hits",
                "value": float(f"{res:.3g}"),
                "unit": "m",
            },
        ]
    if args.json_out:
        write_result(
            args.json_out,
            result_record("bench_terrain", figures, title="Ray/DEM intersection", machine=machine),
        )


if __name__ == "__main__":
    main()
