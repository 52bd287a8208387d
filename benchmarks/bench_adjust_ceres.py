"""planetref's line-scan adjustment side by side with Ceres Solver (``bench_adjust.py --vs ceres``).

The problem is ``bench_adjust.py``'s (3 CCDs, 12 Lagrange nodes of order 4, N MCPs with
known ground, 0.3 px noise; initial attitudes with a bias and a drift; node attitudes
free, positions and interior fixed; plain least squares, no outlier rejection). It is
written to a ``PRCERES1`` file (:mod:`ceres_problem`) and solved by
``benchmarks/ceres/linescan_ba.cc``: one Ceres residual block per observation with
analytic partials of the same model and the same residual (projected minus observed
line and sample over their sigmas, the projected line found by the same chord search),
Levenberg-Marquardt, each of ``--solvers`` (DENSE_SCHUR, SPARSE_SCHUR, ITERATIVE_SCHUR
with SCHUR_JACOBI by default) with 1 and 2 threads. Set-up (Debian, as root)::

    apt-get update && apt-get install -y libceres-dev g++ cmake

The benchmark builds the program itself (once, into ``~/.cache/planetref-bench``) and
skips Ceres with the reason when it cannot.

Stopping rule: Ceres gets planetref's ``ftol`` (1e-12, relative cost change, the same
definition) as ``function_tolerance``, its ``xtol`` (1e-8) as ``parameter_tolerance``
(Ceres's is relative to the parameter norm, planetref's in sigmas: the nearest it has),
``gradient_tolerance`` 0 (planetref has none) and, as initial trust region, the inverse
of planetref's initial damping (1e-8). Both reach the same optimum: ``max_diff_sigma``
is the largest difference of the adjusted attitudes in planetref's sigmas (required
below 0.01). One Ceres run per size also computes the attitude covariance
(``ceres::Covariance``, SPARSE_QR); ``sigma_ratio`` is planetref's sigma over Ceres's
times planetref's sigma0 (Ceres's covariance is of unit weight).

Without unknown points (every point is a known MCP) Ceres's Schur solvers have no point
blocks to eliminate: with the default ordering Ceres eliminates an independent set of
node blocks instead (``linear_solver_ordering_used``, e.g. ``[3, 9]``), and the dense
normal equations (DENSE_NORMAL_CHOLESKY) run as a reference. ``--tie-fraction F`` puts
a share F of the observations on free tie points (``bench_adjust.py --n-tie``: two
observations each in the CCD overlaps, 20 m off at the start): Ceres then eliminates the
points first (ordering ``[points, nodes]``), as planetref's Schur complement does.

Timing: every run is a fresh process (planetref: a worker of this script that builds
the same network from the seed and loads the compiled kernels before the clock starts;
Ceres: the program), run interleaved (for each repeat, for each thread count: planetref,
then each Ceres solver) and summarised by medians. ``planetref_s`` is the whole
:func:`planetref.adjust.adjust` call (set-up, LM, covariance, redundancy, diagnostics);
``ceres_s`` is the program's problem construction (reading excluded; it includes the
first projection of every observation, which seeds the line search as planetref's first
evaluation does) plus ``ceres::Solve``; ``ceres_solve_s`` the solve alone. Peak memory is
each process's ``VmHWM`` (the interpreter, numpy and numba for planetref: see
``planetref_rss_before_mb``, the resident size just before the call). Where the time
goes: Ceres's summary (residual and Jacobian evaluation, linear solver, preprocessor)
and planetref's phases (evaluation and normal equations, reduced system and steps,
statistics, the rest), timed by wrapping the solver's methods.

Usage::

    python benchmarks/bench_adjust.py --vs ceres --sizes 20000,200000,1000000 --repeat 3 \\
        --json --out benchmarks/results/bench_adjust_ceres.json
    python benchmarks/bench_adjust.py --vs ceres --sizes 20000,200000,1000000 --repeat 3 \\
        --tie-fraction 0.5 --json --out benchmarks/results/bench_adjust_ceres_ties.json
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
#: The Schur solvers, and the dense normal equations as a reference (no points to eliminate).
SOLVERS = ("DENSE_SCHUR", "SPARSE_SCHUR", "ITERATIVE_SCHUR", "DENSE_NORMAL_CHOLESKY")
#: planetref's solver settings turned into Ceres options (see the module doc).
CERES_STOP = ("--ftol", "1e-12", "--ptol", "1e-8", "--gtol", "0", "--initial-radius", "1e8")


def vm_kb(field: str) -> float:
    """A ``/proc/self/status`` field in MB (``VmHWM``: peak resident, ``VmRSS``: now)."""
    with open("/proc/self/status", encoding="ascii") as f:
        for line in f:
            if line.startswith(field + ":"):
                return float(line.split()[1]) / 1024.0
    return float("nan")


# ------------------------------------------------------------------ planetref worker
def _phase_timers() -> tuple[dict[str, list[float]], list[tuple[object, str, object]]]:
    """Wrap the solver's methods so that each outermost call adds its wall/CPU time."""
    from planetref.adjust.solver import BundleSolver

    phases = {
        "_linearize": "evaluate_and_normal_equations",
        "_reduced": "reduced_system_and_steps",
        "_solve_reduced": "reduced_system_and_steps",
        "_back_substitute": "reduced_system_and_steps",
        "_statistics": "statistics_covariance",
        "_check_rank": "rank_check",
        "_structure": "layout",
    }
    acc: dict[str, list[float]] = {v: [0.0, 0.0] for v in phases.values()}
    depth = [0]
    saved = []
    for name, phase in phases.items():
        fn = getattr(BundleSolver, name)
        saved.append((BundleSolver, name, fn))

        def wrapped(*a, _fn=fn, _phase=phase, **kw):
            if depth[0]:
                return _fn(*a, **kw)
            depth[0] += 1
            t0, c0 = time.perf_counter(), time.process_time()
            try:
                return _fn(*a, **kw)
            finally:
                acc[_phase][0] += time.perf_counter() - t0
                acc[_phase][1] += time.process_time() - c0
                depth[0] -= 1

        setattr(BundleSolver, name, wrapped)
    return acc, saved


def worker(n_obs: int, seed: int, n_tie: int, out: Path | None) -> dict[str, object]:
    """One planetref adjustment in this process (threads from ``OMP_NUM_THREADS``)."""
    from bench_adjust import CONFIG, build_problem

    from planetref.adjust import adjust
    from planetref.camera.linescan import compiled
    from planetref.runtime.threads import compute_threads

    if compiled.available() and compiled.warm_up():
        # With tie points when the problem has them: their kernels (point elimination,
        # tie rows, redundancy) load from numba's cache here too, not on the clock.
        adjust(build_problem(2000, seed + 1, 0.3, 12, 500 if n_tie else 0)[0], CONFIG)
    net, _ = build_problem(n_obs, seed, 0.3, 12, n_tie)
    acc, saved = _phase_timers()
    rss_before = vm_kb("VmRSS")
    try:
        t0, c0 = time.perf_counter(), time.process_time()
        res = adjust(net, CONFIG)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    finally:
        for cls, name, fn in saved:
            setattr(cls, name, fn)
    phases = {k: {"s": round(v[0], 4), "cpu_s": round(v[1], 4)} for k, v in acc.items()}
    rest = wall - sum(v[0] for v in acc.values())
    phases["other_setup_redundancy_diagnostics"] = {
        "s": round(rest, 4),
        "cpu_s": round(cpu - sum(v[1] for v in acc.values()), 4),
    }
    if out is not None:
        np.savez(out, x=res.x, sigma=res.sigma, mode=res.parameter_mode, sigma0=res.sigma0)
    return {
        "threads": compute_threads(),
        "s": wall,
        "cpu_s": cpu,
        "lm_s": sum(r["seconds"] for r in res.rounds),
        "lm_cpu_s": sum(r["cpu_seconds"] for r in res.rounds),
        "iterations": sum(r["iterations"] for r in res.rounds),
        "evaluations": sum(r["evaluations"] for r in res.rounds),
        "rss_before_mb": rss_before,
        "peak_rss_mb": vm_kb("VmHWM"),
        "rmse_px": res.summary()["rmse_px"],
        "phases": phases,
    }


def run_worker(
    n_obs: int, seed: int, n_tie: int, threads: int, out: Path | None
) -> dict[str, object]:
    env = dict(os.environ)
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        env[var] = str(threads)
    cmd = [sys.executable, str(Path(__file__)), "--worker", str(n_obs), str(seed), str(n_tie)]
    if out is not None:
        cmd.append(str(out))
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"planetref worker failed: {proc.stderr.strip()[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


# ------------------------------------------------------------------------ the bench
def _median(runs: list[dict], key: str) -> float:
    return round(statistics.median(float(r[key]) for r in runs), 4)


def _ceres_row(runs: list[dict]) -> dict[str, object]:
    s0 = runs[0]
    row: dict[str, object] = {
        "s": round(statistics.median(r["build_s"] + r["solve_s"] for r in runs), 4),
        "cpu_s": _median(runs, "total_cpu_s"),
        "solve_s": _median(runs, "solve_s"),
        "solve_cpu_s": _median(runs, "solve_cpu_s"),
        "build_s": _median(runs, "build_s"),
        "process_wall_s": _median(runs, "process_wall_s"),
        "all_s": [round(r["build_s"] + r["solve_s"], 4) for r in runs],
        "peak_rss_mb": round(max(float(r["peak_rss_mb"]) for r in runs), 1),
        "rss_start_mb": round(float(s0["rss_start_mb"]), 1),
    }
    for key in (
        "ceres_preprocessor_s",
        "ceres_minimizer_s",
        "ceres_linear_solver_s",
        "ceres_residual_evaluation_s",
        "ceres_jacobian_evaluation_s",
    ):
        row[key] = _median(runs, key)
    # Ceres's summary times are wall seconds (inflated alike when other jobs share the
    # cores): their shares of the construction + solve are the robust part.
    row["share"] = {
        "problem_construction": round(
            statistics.median(r["build_s"] / (r["build_s"] + r["solve_s"]) for r in runs), 3
        ),
        **{
            key.removeprefix("ceres_").removesuffix("_s"): round(
                statistics.median(r[key] / (r["build_s"] + r["solve_s"]) for r in runs), 3
            )
            for key in (
                "ceres_preprocessor_s",
                "ceres_linear_solver_s",
                "ceres_residual_evaluation_s",
                "ceres_jacobian_evaluation_s",
            )
        },
    }
    for key in (
        "linear_solver_type_used",
        "linear_solver_ordering_used",
        "preconditioner_type_used",
        "num_threads_used",
        "termination",
        "message",
        "iterations",
        "successful_steps",
        "unsuccessful_steps",
        "residual_evaluations",
        "jacobian_evaluations",
        "final_cost",
        "residual_blocks_wider_than_window",
    ):
        row[key] = s0[key]
    return row


def _planetref_row(runs: list[dict]) -> dict[str, object]:
    row: dict[str, object] = {
        k: _median(runs, k) for k in ("s", "cpu_s", "lm_s", "lm_cpu_s", "rss_before_mb")
    }
    row["all_s"] = [round(float(r["s"]), 4) for r in runs]
    row["peak_rss_mb"] = round(max(float(r["peak_rss_mb"]) for r in runs), 1)
    row["iterations"] = runs[0]["iterations"]
    row["evaluations"] = runs[0]["evaluations"]
    row["threads_used"] = runs[0]["threads"]
    row["phases"] = {
        k: {
            "s": round(statistics.median(r["phases"][k]["s"] for r in runs), 4),
            "cpu_s": round(statistics.median(r["phases"][k]["cpu_s"] for r in runs), 4),
        }
        for k in runs[0]["phases"]
    }
    return row


def bench_size(exe: Path | None, n_obs: int, args: argparse.Namespace, log) -> dict[str, object]:
    """Every run of one size (see the module doc); returns its JSON block."""
    import ceres_problem
    from bench_adjust import build_problem

    n_tie = round(args.tie_fraction * n_obs / 2)
    out: dict[str, object] = {"n_obs": n_obs, "n_tie_points": n_tie}
    with tempfile.TemporaryDirectory(prefix="ceres-bench-") as tmp:
        tmpd = Path(tmp)
        problem = tmpd / "problem.bin"
        net, _ = build_problem(n_obs, args.seed, 0.3, 12, n_tie)
        ceres_problem.write_problem(
            ceres_problem.problem_of(net, position_free=False, attitude_free=True), problem
        )
        n_nodes = len(net.cameras[0].nodes)
        del net
        ref = tmpd / "planetref.npz"
        pr: dict[int, list[dict]] = {t: [] for t in args.threads}
        cr: dict[tuple[str, int], list[dict]] = {
            (s, t): [] for s in args.solvers for t in args.threads
        }
        diffs: dict[str, float] = {}
        repeat = args.repeat_large if n_obs >= args.large else args.repeat
        out["repeat"] = repeat
        for rep in range(repeat):
            for t in args.threads:
                r = run_worker(n_obs, args.seed, n_tie, t, ref if rep == 0 else None)
                pr[t].append(r)
                log(f"n={n_obs} rep={rep} threads={t} planetref {r['s']:.3f} s")
                if exe is None:
                    continue
                sol = np.load(ref)
                act = sol["mode"] != 2
                for s in args.solvers:
                    c = ceres_problem.run(exe, problem, n_nodes, s, t, extra=CERES_STOP)
                    summ = dict(c.summary)
                    summ["process_wall_s"] = c.wall_s
                    cr[(s, t)].append(summ)
                    x = np.concatenate([c.nodes.ravel(), sol["x"][6 * n_nodes :]])
                    d = float(np.max(np.abs(x - sol["x"])[act] / sol["sigma"][act]))
                    diffs[s] = max(diffs.get(s, 0.0), d)
                    log(
                        f"n={n_obs} rep={rep} threads={t} {s} "
                        f"{summ['build_s'] + summ['solve_s']:.3f} s, diff {d:.2g} sigma"
                    )
        out["planetref"] = {str(t): _planetref_row(pr[t]) for t in args.threads}
        if exe is None:
            return out
        # One more run: the attitude covariance, against planetref's sigmas.
        sol = np.load(ref)
        act = sol["mode"] != 2
        c = ceres_problem.run(
            exe, problem, n_nodes, args.solvers[0], 1, extra=CERES_STOP, covariance=True
        )
        ratio = sol["sigma"][act] / (c.attitude_sigma * float(sol["sigma0"]))
        out["covariance_check"] = {
            "solver": args.solvers[0],
            "covariance_s": round(float(c.summary["covariance_s"]), 4),
            "covariance_ok": c.summary["covariance_ok"],
            "sigma_ratio_min": float(f"{np.min(ratio):.6g}"),
            "sigma_ratio_max": float(f"{np.max(ratio):.6g}"),
        }
    out["ceres"] = {s: {str(t): _ceres_row(cr[(s, t)]) for t in args.threads} for s in args.solvers}
    out["max_diff_sigma"] = {s: float(f"{v:.3g}") for s, v in diffs.items()}
    out["same_optimum"] = bool(max(diffs.values()) < 0.01)
    ratios: dict[str, object] = {}
    for t in args.threads:
        p = out["planetref"][str(t)]
        rows = {s: out["ceres"][s][str(t)] for s in args.solvers}
        best = min(rows, key=lambda s: rows[s]["s"])
        best_cpu = min(rows, key=lambda s: rows[s]["cpu_s"])
        ratios[str(t)] = {
            "ceres_best": best,
            "ceres_best_s": rows[best]["s"],
            "planetref_s": p["s"],
            # planetref's time over Ceres's best (below 1: planetref is faster) ...
            "planetref_over_ceres": round(p["s"] / rows[best]["s"], 3),
            "planetref_over_ceres_cpu": round(p["cpu_s"] / rows[best_cpu]["cpu_s"], 3),
            "planetref_lm_over_ceres_solve": round(p["lm_s"] / rows[best]["solve_s"], 3),
            # ... and its inverse, planetref's speed-up.
            "speedup": round(rows[best]["s"] / p["s"], 2),
            "speedup_cpu": round(rows[best_cpu]["cpu_s"] / p["cpu_s"], 2),
        }
    out["ratio"] = ratios
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="20000,200000", help="observation counts, comma-separated")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=3, help="interleaved repeats (medians)")
    ap.add_argument(
        "--repeat-large", type=int, default=2, help="repeats of sizes of --large or more"
    )
    ap.add_argument("--large", type=int, default=1_000_000, help="see --repeat-large")
    ap.add_argument("--threads", default="1,2", help="thread counts, comma-separated")
    ap.add_argument(
        "--tie-fraction",
        type=float,
        default=0.0,
        help="share of the observations on free tie points (2 each; Schur-eliminated)",
    )
    ap.add_argument(
        "--solvers",
        default=None,
        help="Ceres linear solvers, comma-separated (default: the Schur solvers, and "
        "DENSE_NORMAL_CHOLESKY without tie points: with them it is dense in the points)",
    )
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    ap.add_argument("--vs", default="ceres", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    args.threads = [int(t) for t in args.threads.split(",")]
    if args.solvers is None:
        args.solvers = ",".join(SOLVERS if args.tie_fraction == 0 else SOLVERS[:3])
    args.solvers = [s.strip().upper() for s in args.solvers.split(",")]
    sizes = [int(float(s)) for s in args.sizes.split(",")]

    import ceres_problem
    from machine import describe

    def log(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    exe, why = ceres_problem.build()
    if exe is None:
        log(f"Ceres skipped: {why}")
    result: dict[str, object] = {
        "benchmark": "bench_adjust --vs ceres"
        + (" (free tie points)" if args.tie_fraction else ""),
        "command": " ".join(["python", f"benchmarks/{Path(sys.argv[0]).name}", *sys.argv[1:]]),
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "machine": describe(),
        "ceres": None if exe is None else "built",
        "ceres_skipped": why or None,
        "stopping": " ".join(CERES_STOP),
        "sizes": [],
    }
    for n in sizes:
        block = bench_size(exe, n, args, log)
        result["sizes"].append(block)
        result["figures"] = headline(result)
        if args.out is not None:  # after each size: a long run keeps what it measured
            args.out.parent.mkdir(parents=True, exist_ok=True)
            tmp = args.out.with_name(args.out.name + ".tmp")
            tmp.write_text(json.dumps(result, indent=1) + "\n")
            os.replace(tmp, args.out)
    if args.json:
        print(json.dumps(result))
    else:
        print_table(result)
    return 0


def headline(result: dict[str, Any]) -> dict[str, dict[str, object]]:
    """The figures the benchmarks page shows, derived from the measured blocks.

    Per size and thread count: planetref's CPU-s, the best Ceres configuration's CPU-s,
    their ratio (below 1: planetref uses less CPU) and the largest parameter difference
    at the optimum in planetref's sigmas.
    """
    out: dict[str, dict[str, object]] = {}
    for b in result.get("sizes", []):
        n = b["n_obs"]
        ties = f", {b['n_tie_points']} tie points" if b.get("n_tie_points") else ""
        for t, r in (b.get("ratio") or {}).items():
            key = f"n={n}{ties}, {t} thread(s)"
            cpu = b["planetref"][t]["cpu_s"]
            best = r["ceres_best"]
            out[f"{key}: planetref CPU"] = {"value": cpu, "unit": "s"}
            out[f"{key}: Ceres best CPU"] = {
                "value": b["ceres"][best][t]["cpu_s"],
                "unit": "s",
                "note": best,
            }
            out[f"{key}: planetref / Ceres best, CPU"] = {
                "value": r["planetref_over_ceres_cpu"],
                "note": "below 1: planetref uses less CPU",
            }
        diffs = b.get("max_diff_sigma") or {}
        if diffs:
            out[f"n={n}{ties}: largest parameter difference"] = {
                "value": max(diffs.values()),
                "unit": "sigma",
                "note": "same optimum" if b.get("same_optimum") else "NOT the same optimum",
            }
    return out


def print_table(result: dict[str, object]) -> None:
    """A readable summary: per size and thread count, planetref and each Ceres solver."""
    print(f"machine: {result['machine']}")
    if result["ceres_skipped"]:
        print(f"Ceres skipped: {result['ceres_skipped']}")
    for b in result["sizes"]:
        print(f"\nN = {b['n_obs']} observations")
        for t, p in b["planetref"].items():
            print(
                f"  {t} thread(s): planetref {p['s']:.3f} s (CPU {p['cpu_s']:.3f} s, "
                f"peak {p['peak_rss_mb']:.0f} MB, {p['iterations']} it)"
            )
            for s, rows in (b.get("ceres") or {}).items():
                c = rows[t]
                print(
                    f"    Ceres {s:<16} {c['s']:.3f} s (CPU {c['cpu_s']:.3f} s, peak "
                    f"{c['peak_rss_mb']:.0f} MB, {c['iterations']} it, used "
                    f"{c['linear_solver_type_used']} {c['linear_solver_ordering_used']}; "
                    f"linear solver {c['ceres_linear_solver_s']:.3f} s, residuals "
                    f"{c['ceres_residual_evaluation_s']:.3f} s, Jacobians "
                    f"{c['ceres_jacobian_evaluation_s']:.3f} s)"
                )
            if "ratio" in b:
                r = b["ratio"][t]
                print(
                    f"    planetref / Ceres best ({r['ceres_best']}): "
                    f"{r['planetref_over_ceres']} wall, {r['planetref_over_ceres_cpu']} CPU "
                    f"(planetref {r['speedup']}x faster)"
                )
        if "max_diff_sigma" in b:
            print(f"  same optimum: {b['same_optimum']} (max diff {b['max_diff_sigma']} sigma)")
            print(f"  covariance check: {b['covariance_check']}")


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        sys.path.insert(0, str(HERE))
        n, seed, n_tie = int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
        dest = Path(sys.argv[5]) if len(sys.argv) > 5 else None
        print(json.dumps(worker(n, seed, n_tie, dest)))
        sys.exit(0)
    sys.exit(main())
