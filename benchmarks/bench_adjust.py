"""Benchmark: planetref's bundle adjustment against scipy.optimize.least_squares.

One synthetic HiRIC-like line-scan problem (3 staggered CCDs of 2048 x 20000 pixels, 12
orientation nodes, 265 km orbit) with N matched control points (known ground, heights
within +-2 km, 0.3 px Gaussian noise on the measures). The initial attitudes carry a
bias and a drift (tens of pixels); the positions are the true orbit and held fixed, the
node attitudes are free, the interior orientation fixed: a well-posed problem that both
solvers can bring to the same optimum. Both minimise the same weighted least-squares
cost (no robust loss, no outlier rejection); scipy runs ``method="trf"`` with the sparse
Jacobian (``tr_solver="lsmr"``, ``x_scale="jac"``, tolerances 1e-12).

scipy's residuals and Jacobian come, by default, from the native camera's public API
(``LineScanCamera.ground_to_image``/``image_partials``, what a scipy user would write):
that is ``scipy_s`` and ``speedup``. ``scipy_same_kernel_s`` and
``speedup_same_kernel`` drive scipy with planetref's own fused projection kernel instead
(the same compiled projection and partials, seeded with the previous lines as the
solver's are), which isolates the solver's share of the speedup (``--scipy-kernel``
picks either or both).

What the times cover. ``planetref_*`` is the whole :func:`planetref.adjust.adjust` call:
set-up, the Levenberg-Marquardt solve, the a-posteriori statistics (covariance,
correlations), the redundancy numbers and the diagnostics and metrics of the result.
``planetref_lm_cpu_s`` is the solve alone (the solver's rounds: linearisations, reduced
systems, steps, covariance). scipy's time is its ``least_squares`` call alone (no
covariance, no diagnostics). ``speedup_cpu_same_kernel`` compares scipy with the whole
adjustment (conservative); ``speedup_cpu_same_kernel_lm`` compares the two solves.
Both stop at the same optimum (``max_param_diff_sigma*``: the largest difference of the
active parameters, in planetref's sigmas). scipy's path (``scipy*_nfev``) depends on
the BLAS threads of its ``lsmr`` (their rounding): with ``OMP_NUM_THREADS=1`` it took 5
evaluations here, with the default threads 16, so its CPU time tripled. The
single-threaded figure is the conservative one.

Usage::

    python benchmarks/bench_adjust.py --n-obs 200000 --json

``--vs ceres`` runs the comparison with Ceres Solver instead (``bench_adjust_ceres.py``:
the same problem solved by a C++ twin of the model, its own options and set-up line).

prints ``{"n_obs", "planetref_s", "scipy_s", "speedup", "max_param_diff_sigma",
"peak_rss_mb", ...}``. ``peak_rss_mb`` is the process's peak resident memory after the
planetref solve (before scipy runs); ``--no-scipy`` skips scipy (e.g. at 1e6).
``--n-tie K`` makes K of the points free tie points seen in the 16-pixel overlaps of
neighbouring CCDs (2 observations each, eliminated by the Schur complement).

Threads: the adjustment evaluates and accumulates its chunks in
:func:`planetref.runtime.threads.compute_threads` threads (``OMP_NUM_THREADS`` when set, else the
cores), printed as ``threads``; ``OMP_NUM_THREADS`` also sets scipy's BLAS threads, so
both sides run under the same thread count (compare ``OMP_NUM_THREADS=1`` and ``=2``).

The projection-and-partials kernel runs compiled (numba) when numba imports, else on
numpy. ``kernel_compiled_s`` / ``kernel_numpy_s`` (CPU) time one full evaluation (projection
and partials of every observation from the observed lines, warm) with each, in the same
run (``kernel_speedup``); ``--kernel numpy`` solves with the numpy references of every
compiled piece (projection kernel, pattern partials, normal-equation accumulation,
point elimination, cofactor products), ``--kernel both`` solves with each and prints
``planetref_numpy_s`` and ``speedup_compiled`` too. ``*_cpu_s`` / ``speedup_cpu*`` are
process CPU times (robust when other jobs share the cores; run with
``OMP_NUM_THREADS=1`` for comparable figures). The first compiled call of a process
loads the kernel from numba's on-disk cache (or compiles it once, a few seconds), and
the other compiled pieces load at their first call: ``jit_load_s`` is both (the kernel,
then one adjustment of 2000 observations), outside every timing.

First call and repeated calls. ``planetref_s`` is the first adjustment of the big
problem in the process, ``planetref_sys_s`` its system (kernel) CPU time. On this
project's machine (a virtual machine whose host takes back the memory a guest frees)
touching memory that no process has used in the last few seconds costs ~4 s per GB
(the same pages touched again: ~0.2 s per GB); the first call pays that for the part
of its memory peak beyond what the process already holds, so its time varies with
what ran before it, and a smaller peak is a shorter call. ``--repeat K`` times the
same call K more times (``planetref_repeat_s``, ``planetref_repeat_sys_s``): warm
memory, the cost of the computation alone.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time

import numpy as np

from planetref.adjust import Network, adjust, linearization, schur
from planetref.camera.linescan import compiled
from planetref.camera.orbit import OrbitGeometry, ccd_row, orbit_camera
from planetref.geometry.geodesy import ray_ellipsoid_intersection
from planetref.runtime.threads import compute_threads


def peak_rss_mb() -> float:
    # ru_maxrss is in kilobytes on Linux.
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def build_problem(n_obs: int, seed: int, noise_px: float, n_nodes: int, n_tie: int = 0):
    ccds = ccd_row(3, 2048, 20000, 0.010, overlap_px=16, stagger_mm=1.0)
    true, _ = orbit_camera(
        OrbitGeometry(20.0, 74.0, 30.0), focal_length_mm=4640.0, ccds=ccds, n_nodes=n_nodes
    )
    rng = np.random.default_rng(seed)
    n_mcp = n_obs - 2 * n_tie
    ccd = rng.integers(0, 3, n_mcp)
    line = rng.uniform(0.0, 20000.0, n_mcp)
    sample = rng.uniform(0.0, 2048.0, n_mcp)
    xyz = np.empty((n_mcp, 3))
    for k in range(3):
        m = ccd == k
        o, d = true.look_rays(line[m], sample[m], ccd=f"ccd{k + 1}")
        s = ray_ellipsoid_intersection(o, d, true.ellipsoid, rng.uniform(-2000, 2000, m.sum()))
        xyz[m] = o + s[:, None] * d
    # Tie points in the 16-pixel overlaps of neighbouring CCDs (ccd1/ccd2, ccd2/ccd3).
    pair = rng.integers(0, 2, n_tie)
    t_line = rng.uniform(500.0, 19500.0, n_tie)
    t_sample = rng.uniform(2048 - 14, 2048 - 2, n_tie)
    t_xyz = np.empty((n_tie, 3))
    t_obs = np.empty((n_tie, 2))
    for k in range(2):
        m = pair == k
        o, d = true.look_rays(t_line[m], t_sample[m], ccd=f"ccd{k + 1}")
        s = ray_ellipsoid_intersection(o, d, true.ellipsoid, rng.uniform(-2000, 2000, m.sum()))
        t_xyz[m] = o + s[:, None] * d
        ip = true.ground_to_image(t_xyz[m], ccd=f"ccd{k + 2}")
        t_obs[m] = np.stack([ip.line, ip.sample], 1)
    nodes = true.nodes.copy()
    t = np.linspace(-1.0, 1.0, n_nodes)[:, None]
    nodes[:, 3:] += np.array([2e-5, -3e-5, 1e-5]) + t * np.array([4e-6, 6e-6, -3e-6])
    init = true.replace(nodes=nodes)
    m_all = n_mcp + 2 * n_tie
    point = np.concatenate([np.arange(n_mcp), n_mcp + np.arange(n_tie), n_mcp + np.arange(n_tie)])
    obs_ccd = np.concatenate([ccd, pair, pair + 1])
    obs_line = np.concatenate([line, t_line, t_obs[:, 0]]) + rng.normal(0.0, noise_px, m_all)
    obs_sample = np.concatenate([sample, t_sample, t_obs[:, 1]]) + rng.normal(0.0, noise_px, m_all)
    # Tie points start 20 m off and are free; MCP ground is known.
    p_xyz = np.concatenate([xyz, t_xyz + rng.normal(0.0, 20.0, t_xyz.shape)])
    p_sig = np.concatenate([np.zeros((n_mcp, 3)), np.full((n_tie, 3), np.inf)])
    net = Network(
        cameras=(init,),
        camera_ids=("strip",),
        point_ids=np.array([f"p{i}" for i in range(n_mcp + n_tie)]),
        point_xyz=p_xyz,
        point_sigma_m=p_sig,
        point_kind=np.array(["mcp"] * n_mcp + ["tie"] * n_tie),
        obs_camera=np.zeros(m_all, np.intp),
        obs_ccd=obs_ccd,
        obs_point=point,
        obs_line=obs_line,
        obs_sample=obs_sample,
        obs_sigma_px=np.full(m_all, noise_px),
        obs_check=np.zeros(m_all, bool),
        obs_ids=np.array([], dtype=str),
    )
    return net, true


def time_kernel(net: Network, use_compiled: bool, repeat: int = 2) -> float:
    """Best-of-``repeat`` CPU seconds of one projection-with-partials pass over every obs."""
    cam = net.cameras[0]
    kern = cam.kernel
    poly = kern.eo_poly(cam.nodes)
    io = cam.interior.as_array()
    best = float("inf")
    for _ in range(repeat):
        t0 = time.process_time()
        for k, ccd in enumerate(cam.ccds):
            sel = net.obs_ccd == k
            p = net.point_xyz[net.obs_point[sel]]
            kern.project_with_partials(
                poly, io, ccd, p, net.obs_line[sel], None, use_compiled=use_compiled
            )
        best = min(best, time.process_time() - t0)
    return best


def solve(net: Network, use_compiled: bool) -> tuple[object, float, float, float]:
    """``adjust`` compiled or on the numpy references: result, wall, CPU and system seconds.

    The system seconds are the kernel's share of the CPU time (page faults: on a
    virtual machine whose host reclaims freed memory, touching memory the process has
    not used before is costly; see the module doc).
    """
    loaders = [(compiled, "available"), (linearization, "_compiled"), (schur, "_compiled")]
    saved = [getattr(mod, name) for mod, name in loaders]
    if not use_compiled:  # the numpy references
        compiled.available = lambda: False
        linearization._compiled = lambda: None
        schur._compiled = lambda: None
    try:
        s0 = resource.getrusage(resource.RUSAGE_SELF).ru_stime
        t0, c0 = time.perf_counter(), time.process_time()
        res = adjust(net, CONFIG)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        return res, wall, cpu, resource.getrusage(resource.RUSAGE_SELF).ru_stime - s0
    finally:
        for (mod, name), fn in zip(loaders, saved, strict=True):
            setattr(mod, name, fn)


CONFIG = {
    "linescan": {
        "position": {"mode": "fixed"},
        "attitude": {"mode": "free"},
        "interior": {"mode": "fixed"},
    },
    # From the same start as scipy and Ceres (no rigid first solve: they have none).
    "solver": {"loss": "linear", "rigid_start": False},
    "outliers": {"enabled": False},
    # The solver alone: the same weights as scipy gets (no variance components).
    "variance": {"enabled": False},
}


def main(argv: list[str] | None = None) -> int:
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--vs", choices=["scipy", "ceres"], default="scipy")
    known, rest = pre.parse_known_args(argv)
    if known.vs == "ceres":  # its own options: bench_adjust_ceres.py --help
        from bench_adjust_ceres import main as vs_ceres

        return vs_ceres(rest)
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--vs",
        choices=["scipy", "ceres"],
        default="scipy",
        help="the peer: scipy (this script) or Ceres Solver (bench_adjust_ceres.py)",
    )
    ap.add_argument("--n-obs", type=int, default=200_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--noise-px", type=float, default=0.3)
    ap.add_argument("--n-nodes", type=int, default=12)
    ap.add_argument(
        "--n-tie",
        type=int,
        default=0,
        help="tie points (free XYZ, 2 observations each) among the N observations",
    )
    ap.add_argument("--no-scipy", action="store_true", help="skip scipy (large N)")
    ap.add_argument(
        "--scipy-kernel",
        choices=["camera", "planetref", "both"],
        default="both",
        help="residual/Jacobian source of the scipy runs",
    )
    ap.add_argument(
        "--kernel",
        choices=["compiled", "numpy", "both"],
        default="compiled",
        help="projection kernel of the planetref solve (compiled falls back to numpy)",
    )
    ap.add_argument(
        "--repeat",
        type=int,
        default=0,
        help="time the planetref call this many more times in the same process",
    )
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    has_jit = compiled.available() and compiled.warm_up()
    if has_jit:
        # Every other compiled piece (normal equations, sorting, metrics) is loaded by
        # its first call: one small adjustment loads them all, outside the timing.
        adjust(build_problem(2000, args.seed + 1, args.noise_px, args.n_nodes, 0)[0], CONFIG)
    jit_load_s = time.perf_counter() - t0

    t0 = time.perf_counter()
    net, true = build_problem(args.n_obs, args.seed, args.noise_px, args.n_nodes, args.n_tie)
    build_s = time.perf_counter() - t0

    kernel_compiled_s = time_kernel(net, True) if has_jit else None
    kernel_numpy_s = time_kernel(net, False)
    planetref_numpy_s = cpu_numpy = None
    if args.kernel in ("numpy", "both") or not has_jit:
        res, planetref_numpy_s, cpu_numpy, _ = solve(net, False)
    compiled_run = args.kernel != "numpy" and has_jit
    if compiled_run:
        res, planetref_s, planetref_cpu, planetref_sys = solve(net, True)
    else:
        planetref_s, planetref_cpu, planetref_sys = planetref_numpy_s, cpu_numpy, None
    rss = peak_rss_mb()
    # The same call again in the same process: its memory is then warm (see the doc).
    again = [solve(net, compiled_run)[1:] for _ in range(args.repeat)]
    act = res.parameter_mode != 2
    true_x = np.concatenate([true.nodes.ravel(), true.interior.as_array()])
    err_sigma = float(np.max(np.abs(res.x - true_x)[act] / res.sigma[act]))

    out = {
        "n_obs": args.n_obs,
        "n_tie_points": args.n_tie,
        "threads": compute_threads(),
        "planetref_s": round(planetref_s, 3),
        "planetref_cpu_s": round(planetref_cpu, 3),
        "planetref_sys_s": None if planetref_sys is None else round(planetref_sys, 3),
        "planetref_repeat_s": [round(a[0], 3) for a in again],
        "planetref_repeat_sys_s": [round(a[2], 3) for a in again],
        "scipy_s": None,
        "speedup": None,
        "max_param_diff_sigma": None,
        "peak_rss_mb": round(rss, 1),
        "planetref_lm_cpu_s": round(sum(r["cpu_seconds"] for r in res.rounds), 3),
        "planetref_iterations": sum(r["iterations"] for r in res.rounds),
        "planetref_evaluations": sum(r["evaluations"] for r in res.rounds),
        "rmse_px": res.summary()["rmse_px"],
        "rmse_px_before": res.summary()["rmse_px_before"],
        "max_error_vs_truth_sigma": round(err_sigma, 3),
        "build_s": round(build_s, 3),
        "compiled_kernel": has_jit,
        "jit_load_s": round(jit_load_s, 3),
        "kernel_compiled_s": None if kernel_compiled_s is None else round(kernel_compiled_s, 3),
        "kernel_numpy_s": round(kernel_numpy_s, 3),
        "kernel_speedup": (
            None if kernel_compiled_s is None else round(kernel_numpy_s / kernel_compiled_s, 2)
        ),
        "planetref_numpy_s": None if planetref_numpy_s is None else round(planetref_numpy_s, 3),
        "planetref_numpy_cpu_s": None if cpu_numpy is None else round(cpu_numpy, 3),
        "speedup_compiled": (
            round(planetref_numpy_s / planetref_s, 2)
            if planetref_numpy_s is not None and args.kernel == "both"
            else None
        ),
        "speedup_compiled_cpu": (
            round(cpu_numpy / planetref_cpu, 2)
            if cpu_numpy is not None and args.kernel == "both"
            else None
        ),
    }
    if not args.no_scipy:
        from planetref.adjust.reference import solve_with_scipy

        kernels = ["camera", "planetref"] if args.scipy_kernel == "both" else [args.scipy_kernel]
        for kernel in kernels:
            t0, c0 = time.perf_counter(), time.process_time()
            c, _, sp = solve_with_scipy(net, CONFIG, kernel=kernel)
            scipy_s, scipy_cpu = time.perf_counter() - t0, time.process_time() - c0
            diff = float(f"{np.max(np.abs(res.x - c)[act] / res.sigma[act]):.3g}")
            tag = "" if kernel == "camera" else "_same_kernel"
            out.update(
                {
                    f"scipy{tag}_s": round(scipy_s, 3),
                    f"speedup{tag}": round(scipy_s / planetref_s, 2),
                    f"speedup_cpu{tag}": round(scipy_cpu / planetref_cpu, 2),
                    f"speedup_cpu{tag}_lm": round(scipy_cpu / out["planetref_lm_cpu_s"], 2),
                    f"scipy{tag}_cpu_s": round(scipy_cpu, 3),
                    f"max_param_diff_sigma{tag}": diff,
                    f"scipy{tag}_nfev": int(sp.nfev),
                    f"scipy{tag}_status": int(sp.status),
                }
            )
        if "max_param_diff_sigma" not in out or out["max_param_diff_sigma"] is None:
            out["max_param_diff_sigma"] = out.get("max_param_diff_sigma_same_kernel")
            out["scipy_s"] = out.get("scipy_same_kernel_s")
            out["speedup"] = out.get("speedup_same_kernel")
        out["peak_rss_mb_with_scipy"] = round(peak_rss_mb(), 1)
    from machine import describe

    out["machine"] = describe()
    if args.json:
        print(json.dumps(out))
    else:
        for k, v in out.items():
            print(f"{k:>28}: {v}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
