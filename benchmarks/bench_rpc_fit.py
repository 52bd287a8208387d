"""RPC refit of a simulated strip camera: BLAS threads vs a single-threaded BLAS.

Fits an RPC to each CCD of a three-CCD orbital line-scan camera (HiRIC-like layout) with
torch loaded and its intra-op threads busy in a background thread (as in the pipeline,
where matchers run while cameras are refitted), once with numpy's BLAS at its default
thread count and once inside :func:`planetref.runtime.blas.single_threaded_blas` (what
``fit_rpc`` does). Prints the median time per least-squares solve and per fit.
Run without OMP_NUM_THREADS set: ``python benchmarks/bench_rpc_fit.py [--json-out FILE]``
(``--json-out`` also writes the figures, the machine, date and command as JSON for the
documentation's benchmarks page).
"""

from __future__ import annotations

import argparse
import contextlib
import threading
import time

import numpy as np

import planetref.camera.rpc.fit as fit_mod
from planetref.camera.orbit import OrbitGeometry, ccd_row, orbit_camera


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json-out", help="also write the figures as JSON to this file")
    args = ap.parse_args()
    from machine import describe, result_record, write_result

    machine = describe()  # the load before this run's own work
    ccds = ccd_row(3, 4096, 20000, 0.007, overlap_px=48)
    cam, _ = orbit_camera(OrbitGeometry(20.0, 74.0, 30.0), focal_length_mm=4640.0, ccds=ccds)
    stop = threading.Event()
    worker = None
    try:
        import torch

        def busy() -> None:
            a = torch.randn(512, 512)
            while not stop.is_set():
                a = (a @ a).tanh()

        worker = threading.Thread(target=busy, daemon=True)
        worker.start()
        torch_note = f"torch busy on {torch.get_num_threads()} threads"
    except ImportError:  # pragma: no cover
        torch_note = "torch not installed"
    original_solve = fit_mod._solve_rational
    original_ctx = fit_mod.single_threaded_blas
    times: list[float] = []
    figures: list[dict[str, object]] = []
    medians: dict[str, float] = {}

    def timed(*args, **kwargs):
        t0 = time.perf_counter()
        out = original_solve(*args, **kwargs)
        times.append(time.perf_counter() - t0)
        return out

    fit_mod._solve_rational = timed
    try:
        for label, ctx in (
            ("default BLAS threads", contextlib.nullcontext),
            ("single-threaded BLAS", None),
        ):
            fit_mod.single_threaded_blas = ctx if ctx is not None else original_ctx
            times.clear()
            fits = []
            for _ in range(2):
                for ccd in cam.ccd_names:
                    t0 = time.perf_counter()
                    fit_mod.fit_rpc(cam, ccd=ccd, height_range_m=(-3000.0, 3000.0))
                    fits.append(time.perf_counter() - t0)
            medians[label] = float(np.median(times))
            figures += [
                {
                    "name": f"solve median, {label}",
                    "value": round(1e3 * np.median(times), 2),
                    "unit": "ms",
                },
                {
                    "name": f"fit median, {label}",
                    "value": round(float(np.median(fits)), 4),
                    "unit": "s",
                    "note": "wall",
                },
            ]
            print(
                f"{label:>22}: solve median {1e3 * np.median(times):7.1f} ms "
                f"(max {1e3 * np.max(times):7.1f}), fit median {np.median(fits):.3f} s"
            )
    finally:
        fit_mod._solve_rational = original_solve
        fit_mod.single_threaded_blas = original_ctx
        stop.set()
        if worker is not None:
            worker.join()  # a torch thread still running at exit aborts the interpreter
    print(torch_note)
    ratio = medians["default BLAS threads"] / medians["single-threaded BLAS"]
    print(f"solve median, default threads / single: {ratio:.2f}")
    figures.append(
        {
            "name": "solve median ratio, default BLAS threads / single",
            "value": round(ratio, 2),
            "note": f"same run; {torch_note}",
        }
    )
    if args.json_out:
        write_result(
            args.json_out,
            result_record("bench_rpc_fit", figures, title="RPC fit: BLAS threads", machine=machine),
        )


if __name__ == "__main__":
    main()
