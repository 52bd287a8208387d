"""The CPU seconds and wall of ``planetref demo``, per matcher and in all, on a named machine.

For each preset (``--presets tiny hiric-strip``) the scene is simulated once
(``planetref simulate``, timed apart: the demo caches it), then ``planetref demo`` runs
once per matcher (``--matchers NAME``, each in its own process and folder, the cached
scene linked in), and with ``--together`` once more with all of them in one process (what
a user types: ``planetref demo --preset tiny``). Per run it reports:

* ``cpu_s``: CPU seconds of the demo process and its children (user + system, from
  ``getrusage(RUSAGE_CHILDREN)``), which other jobs on the machine do not inflate;
* ``wall_s``: its wall-clock seconds, which they do (the load average when the benchmark
  started is in the JSON's ``machine``);
* ``idle_wall_s``: an estimate of the wall on an idle machine with ``cores`` cores,
  ``cpu_s / cores``. It assumes the demo keeps every core busy (torch, OpenCV and the
  adjustment run multi-threaded; the tile loop is in process), so it is a lower bound:
  single-threaded stretches (the scene's I/O, the reports) take longer;
* the matcher's NCP and its true geolocation error after the adjustment
  (``report.json``: ``matching.ncp``, ``check.geoloc_rmse_m``), so that a faster run is
  seen to find the same;
* the one-off compile of the numba kernels that the run reports apart
  (``timing_s.compile``, wall seconds; zero when the on-disk cache is warm).

Usage::

    python benchmarks/bench_demo.py [--presets tiny] [--matchers all] [--seed 0]
        [--threads 2] [--together] [--work DIR] [--json-out benchmarks/results/bench_demo.json]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

PYTHON = sys.executable


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _run(cmd: list[str], log: Path) -> tuple[float, float, int]:
    """Run ``cmd`` (output to ``log``); ``(cpu_s, wall_s, returncode)``."""
    c0, t0 = _children_cpu(), time.perf_counter()
    with open(log, "w", encoding="utf-8") as f:
        rc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, check=False).returncode
    return _children_cpu() - c0, time.perf_counter() - t0, rc


def _reports(compare_dir: Path) -> dict[str, dict[str, object]]:
    """Per matcher: NCP, true error and compile seconds from its ``report.json``."""
    out: dict[str, dict[str, object]] = {}
    for rep in sorted(compare_dir.glob("runs/*/report.json")):
        doc = json.loads(rep.read_text(encoding="utf-8"))
        out[str(doc.get("matcher", rep.parent.name))] = {
            "ncp": doc.get("matching", {}).get("ncp"),
            "true_rmse_m": doc.get("check", {}).get("geoloc_rmse_m"),
            "compile_s": doc.get("timing_s", {}).get("compile", 0.0),
        }
    return out


def _available(names: list[str]) -> list[str]:
    from planetref.matching.registry import MATCHERS
    from planetref.matching.weights import missing_weights

    if names == ["all"]:
        names = list(MATCHERS)
    return [n for n in names if not missing_weights(MATCHERS[n].weights)]


def bench_preset(
    preset: str,
    matchers: list[str],
    seed: int,
    threads: int,
    work: Path,
    together: bool | str,
) -> dict[str, object]:
    """Simulate ``preset`` once, then run the demo per matcher (and all together)."""
    cli = [PYTHON, "-m", "planetref"]
    scene = work / f"scene-{preset}-seed{seed}"
    sim = {"cpu_s": 0.0, "wall_s": 0.0}
    if not (scene / "scene.toml").is_file():
        cpu, wall, rc = _run(
            [*cli, "simulate", "--preset", preset, "--seed", str(seed), str(scene)],
            work / f"simulate-{preset}.log",
        )
        if rc:
            raise SystemExit(f"bench_demo: simulating {preset} failed (see {work})")
        sim = {"cpu_s": cpu, "wall_s": wall}
    runs: dict[str, dict[str, object]] = {}
    jobs = [] if together == "only" else [(m, [m]) for m in matchers]
    jobs += [("all", matchers)] if together else []
    for label, names in jobs:
        out = work / f"demo-{preset}-{label}"
        out.mkdir(parents=True, exist_ok=True)
        link = out / scene.name
        if not link.exists():
            link.symlink_to(scene.resolve(), target_is_directory=True)
        cmd = [
            *cli,
            "demo",
            "--preset",
            preset,
            "--seed",
            str(seed),
            "--matchers",
            ",".join(names),
            "--threads",
            str(threads),
            "--out",
            str(out),
            "--overwrite",
        ]
        cpu, wall, rc = _run(cmd, out / "demo.log")
        found = _reports(out / f"compare-{preset}-seed{seed}")
        run: dict[str, object] = {"cpu_s": cpu, "wall_s": wall, "returncode": rc}
        if label != "all":
            run.update(found.get(label, {}))
        else:
            run["matchers"] = found
        runs[label] = run
        print(f"{preset} {label}: {json.dumps(run)}", file=sys.stderr, flush=True)
    return {"preset": preset, "seed": seed, "simulate": sim, "runs": runs}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--presets", nargs="+", default=["tiny"])
    ap.add_argument("--matchers", nargs="+", default=["all"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=None, help="default: the cores available")
    ap.add_argument("--together", action="store_true", help="also one demo with all matchers")
    ap.add_argument(
        "--together-only", action="store_true", help="only the one demo with all matchers"
    )
    ap.add_argument("--work", type=Path, default=None, help="keep the runs here (default: temp)")
    ap.add_argument("--json-out", default=None, help="write the result record here")
    args = ap.parse_args(argv)
    from machine import describe, result_record, write_result

    machine = describe()  # the load before this run's own work
    cores = int(machine["cores"] or 1)  # type: ignore[call-overload]
    threads = args.threads or cores
    matchers = _available(args.matchers)
    env_note = os.environ.get("PLANETREF_WEIGHTS", "")
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        for preset in args.presets:
            together = "only" if args.together_only else args.together
            results.append(bench_preset(preset, matchers, args.seed, threads, work, together))
    figures: list[dict[str, object]] = []
    print(f"machine: {machine['cpu']}, {cores} cores, load {machine['load_1min']} at the start")
    print("| preset | matcher | CPU-s | wall s | idle wall est. s | NCP | true RMSE m |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for res in results:
        preset = res["preset"]
        runs: dict[str, dict[str, object]] = res["runs"]  # type: ignore[assignment]
        per = {k: v for k, v in runs.items() if k != "all"}
        total_cpu = sum(float(v["cpu_s"]) for v in per.values())  # type: ignore[arg-type]
        total_wall = sum(float(v["wall_s"]) for v in per.values())  # type: ignore[arg-type]
        for label, run in per.items():
            cpu, wall = float(run["cpu_s"]), float(run["wall_s"])  # type: ignore[arg-type]
            print(
                f"| {preset} | {label} | {cpu:.0f} | {wall:.0f} | {cpu / cores:.0f} | "
                f"{run.get('ncp')} | {run.get('true_rmse_m')} |"
            )
            figures += [
                {"name": f"{preset} {label} CPU", "value": round(cpu, 1), "unit": "CPU-s"},
                {"name": f"{preset} {label} wall", "value": round(wall, 1), "unit": "s"},
                {"name": f"{preset} {label} NCP", "value": run.get("ncp")},
                {
                    "name": f"{preset} {label} true RMSE",
                    "value": run.get("true_rmse_m"),
                    "unit": "m",
                },
            ]
        if per:
            print(
                f"| {preset} | sum of the {len(per)} runs | {total_cpu:.0f} | {total_wall:.0f} | "
                f"{total_cpu / cores:.0f} | | |"
            )
            figures += [
                {
                    "name": f"{preset} sum of per-matcher runs CPU",
                    "value": round(total_cpu, 1),
                    "unit": "CPU-s",
                },
                {
                    "name": f"{preset} idle wall estimate (CPU-s / {cores} cores)",
                    "value": round(total_cpu / cores, 1),
                    "unit": "s",
                    "note": "a lower bound: assumes every core busy throughout",
                },
            ]
        if "all" in runs:
            a = runs["all"]
            cpu, wall = float(a["cpu_s"]), float(a["wall_s"])  # type: ignore[arg-type]
            print(
                f"| {preset} | all in one demo | {cpu:.0f} | {wall:.0f} | {cpu / cores:.0f} | | |"
            )
            figures += [
                {
                    "name": f"{preset} demo (all matchers) CPU",
                    "value": round(cpu, 1),
                    "unit": "CPU-s",
                },
                {
                    "name": f"{preset} demo (all matchers) wall",
                    "value": round(wall, 1),
                    "unit": "s",
                    "note": f"load {machine['load_1min']} at the start",
                },
                {
                    "name": f"{preset} demo (all matchers) idle wall estimate",
                    "value": round(cpu / cores, 1),
                    "unit": "s",
                    "note": f"CPU-s / {cores} cores, a lower bound",
                },
            ]
        sim = res["simulate"]
        print(f"{preset}: simulation {sim['cpu_s']:.0f} CPU-s, {sim['wall_s']:.0f} s (apart)")  # type: ignore[index]
    if args.json_out:
        record = result_record(
            Path(args.json_out).stem,
            figures,
            title="planetref demo: CPU seconds and wall per matcher",
            machine=machine,
        )
        record["details"] = {"results": results, "threads": threads, "weights": bool(env_note)}
        write_result(args.json_out, record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
