"""The line-scan adjustment problem as a file for the Ceres twin (benchmarks/ceres/).

``bench_adjust.py --vs ceres`` writes the network it adjusts with planetref into one raw
binary file, builds the C++ program ``benchmarks/ceres/linescan_ba.cc`` against Ceres
Solver (Debian: ``apt-get update && apt-get install -y libceres-dev g++ cmake``; not a
dependency of planetref) and runs it on that file.

File format ``PRCERES1`` (little-endian; ``N`` nodes, ``R`` line-rate rows, ``C`` CCDs,
``P`` points, ``M`` observations)::

    8 bytes   b"PRCERES1"
    int64[8]  N, k (Lagrange order), R, C, P, M, positions free (0/1), attitudes free (0/1)
    f64[2]    line_lo, line_hi: the lines a projection may reach (the kernel's span)
    f64[R,3]  line-rate rows (start line, start time s, period s/line)
    f64[N]    node times (s)
    f64[3,3]  R0 (row-major)
    f64[N,6]  nodes: X, Y, Z (m), phi, omega, kappa (rad)
    f64[3]    interior x0, y0, f (mm)
    f64[C,4]  CCDs: x_mm, y_mm, angle_rad, pixel_pitch_mm
    f64[P,3]  ground points (m, body-fixed): known (MCPs) or initial values (tie points)
    f64[M]    observed lines, then f64[M] samples
    f64[M,2]  sigmas of (line, sample) (px)
    int32[M]  CCD index, then int32[M] point index
    int32[P]  1 where the point is unknown (a free tie point, eliminated first by the
              Schur solvers), 0 where it is known

The program writes the adjusted nodes (f64[N,6]) and, with ``--covariance``, the
attitude sigmas (f64[N,3], unit weight; NaN without) into ``--out``, and one JSON
object (Ceres's summary, times, peak memory) on stdout.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from planetref.adjust import Network
from planetref.camera.linescan import LineScanCamera

MAGIC = b"PRCERES1"
SOURCE_DIR = Path(__file__).resolve().parent / "ceres"
#: The set-up line printed when the build fails.
SETUP = "apt-get update && apt-get install -y libceres-dev g++ cmake"

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class CeresProblem:
    """The content of a ``PRCERES1`` file (see the module doc)."""

    k: int
    position_free: bool
    attitude_free: bool
    line_range: F64
    line_rates: F64
    node_times: F64
    frame_rotation: F64
    nodes: F64
    interior: F64
    ccds: F64
    points: F64
    obs_line: F64
    obs_sample: F64
    obs_sigma: F64
    obs_ccd: NDArray[np.int32]
    obs_point: NDArray[np.int32]
    point_free: NDArray[np.int32]


def problem_of(net: Network, *, position_free: bool, attitude_free: bool) -> CeresProblem:
    """The Ceres problem of a one-strip network of known and unknown points.

    Args:
        net: A network with one :class:`LineScanCamera`, interior held fixed, whose
            points are known (MCPs, zero ground sigma) or unknown (tie points, infinite
            sigma); weighted ground (finite non-zero sigma) is not modelled.
        position_free: Whether node positions are adjusted.
        attitude_free: Whether node attitudes are adjusted.

    Raises:
        ValueError: When the network is outside what the C++ twin models.
    """
    if len(net.cameras) != 1 or not isinstance(net.cameras[0], LineScanCamera):
        raise ValueError("the Ceres twin models one line-scan camera")
    cam = net.cameras[0]
    sig = np.asarray(net.point_sigma_m, np.float64).reshape(len(net.point_xyz), -1)
    known, free = np.all(sig == 0.0, axis=1), np.all(np.isinf(sig), axis=1)
    if not np.all(known | free):
        raise ValueError(
            "the Ceres twin models known (sigma 0) or unknown (sigma inf) ground points only"
        )
    if any(any(c.distortion) for c in cam.ccds):
        raise ValueError("the Ceres twin models CCDs without lens distortion")
    kern = cam.kernel
    return CeresProblem(
        k=int(kern.k),
        position_free=position_free,
        attitude_free=attitude_free,
        line_range=np.array([kern.line_lo, kern.line_hi]),
        line_rates=np.asarray(cam.line_rates.rows, np.float64).reshape(-1, 3),
        node_times=np.asarray(kern.windows.times, np.float64),
        frame_rotation=np.asarray(cam.frame_rotation, np.float64),
        nodes=np.asarray(cam.nodes, np.float64),
        interior=cam.interior.as_array(),
        ccds=np.array([[c.x_mm, c.y_mm, c.angle_rad, c.pixel_pitch_mm] for c in cam.ccds]),
        points=np.asarray(net.point_xyz, np.float64),
        obs_line=np.asarray(net.obs_line, np.float64),
        obs_sample=np.asarray(net.obs_sample, np.float64),
        obs_sigma=np.broadcast_to(
            np.asarray(net.obs_sigma_px, np.float64).reshape(len(net.obs_line), -1),
            (len(net.obs_line), 2),
        ).copy(),
        obs_ccd=np.asarray(net.obs_ccd, np.int32),
        obs_point=np.asarray(net.obs_point, np.int32),
        point_free=free.astype(np.int32),
    )


def _arrays(p: CeresProblem) -> list[NDArray]:
    f = np.float64
    return [
        p.line_range.astype(f),
        p.line_rates.astype(f),
        p.node_times.astype(f),
        p.frame_rotation.astype(f),
        p.nodes.astype(f),
        p.interior.astype(f),
        p.ccds.astype(f),
        p.points.astype(f),
        p.obs_line.astype(f),
        p.obs_sample.astype(f),
        p.obs_sigma.astype(f),
        p.obs_ccd.astype(np.int32),
        p.obs_point.astype(np.int32),
        p.point_free.astype(np.int32),
    ]


def write_problem(p: CeresProblem, path: Path) -> None:
    """Write ``p`` as a ``PRCERES1`` file (a temporary name, then renamed)."""
    header = np.array(
        [
            len(p.nodes),
            p.k,
            len(p.line_rates),
            len(p.ccds),
            len(p.points),
            len(p.obs_line),
            int(p.position_free),
            int(p.attitude_free),
        ],
        np.int64,
    )
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(MAGIC)
        f.write(header.astype("<i8").tobytes())
        for a in _arrays(p):
            f.write(np.ascontiguousarray(a, a.dtype.newbyteorder("<")).tobytes())
    os.replace(tmp, path)


def read_problem(path: Path) -> CeresProblem:
    """Read a ``PRCERES1`` file.

    Raises:
        ValueError: When the file is not one or is truncated.
    """
    buf = Path(path).read_bytes()
    if buf[:8] != MAGIC:
        raise ValueError(f"{path}: not a PRCERES1 file")
    n, k, r, c, npt, m, pos, att = (int(v) for v in np.frombuffer(buf, "<i8", 8, 8))
    at = 72

    def take(count: int, dtype: str, shape: tuple[int, ...]) -> NDArray:
        nonlocal at
        size = np.dtype(dtype).itemsize * count
        if at + size > len(buf):
            raise ValueError(f"{path}: truncated")
        a = np.frombuffer(buf, dtype, count, at).reshape(shape).copy()
        at += size
        return a

    out = CeresProblem(
        k=k,
        position_free=bool(pos),
        attitude_free=bool(att),
        line_range=take(2, "<f8", (2,)),
        line_rates=take(3 * r, "<f8", (r, 3)),
        node_times=take(n, "<f8", (n,)),
        frame_rotation=take(9, "<f8", (3, 3)),
        nodes=take(6 * n, "<f8", (n, 6)),
        interior=take(3, "<f8", (3,)),
        ccds=take(4 * c, "<f8", (c, 4)),
        points=take(3 * npt, "<f8", (npt, 3)),
        obs_line=take(m, "<f8", (m,)),
        obs_sample=take(m, "<f8", (m,)),
        obs_sigma=take(2 * m, "<f8", (m, 2)),
        obs_ccd=take(m, "<i4", (m,)),
        obs_point=take(m, "<i4", (m,)),
        point_free=take(npt, "<i4", (npt,)),
    )
    if at != len(buf):
        raise ValueError(f"{path}: {len(buf) - at} trailing bytes")
    return out


# ---------------------------------------------------------------------- the build
def cache_dir() -> Path:
    """Where the program is built: ``$XDG_CACHE_HOME/planetref-bench`` (outside the repo)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "planetref-bench"


def build(quiet: bool = True) -> tuple[Path | None, str]:
    """Build ``linescan_ba`` (once per source version): ``(executable, "")`` or ``(None, why)``.

    The build folder is named by a hash of the sources, so an edited source is rebuilt
    and a built one is reused.
    """
    digest = hashlib.sha256()
    for name in ("CMakeLists.txt", "linescan_ba.cc"):
        digest.update((SOURCE_DIR / name).read_bytes())
    folder = cache_dir() / f"ceres-{digest.hexdigest()[:16]}"
    exe = folder / "linescan_ba"
    if exe.is_file():
        return exe, ""
    if shutil.which("cmake") is None or shutil.which("g++") is None:
        return None, f"cmake or g++ not found (set-up: {SETUP})"
    folder.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="build-", dir=folder.parent))
    try:
        for cmd in (
            ["cmake", "-S", str(SOURCE_DIR), "-B", str(work), "-DCMAKE_BUILD_TYPE=Release"],
            ["cmake", "--build", str(work), "-j", "2"],
        ):
            run = subprocess.run(cmd, capture_output=True, text=True, check=False)
            if run.returncode != 0:
                tail = (run.stderr or run.stdout).strip().splitlines()[-3:]
                return None, f"Ceres build failed ({' | '.join(tail)}); set-up: {SETUP}"
        try:
            os.replace(work, folder)  # atomic: a concurrent build leaves one folder
        except OSError:
            pass
    finally:
        if work.exists():
            shutil.rmtree(work, ignore_errors=True)
    return (exe, "") if exe.is_file() else (None, "Ceres build produced no executable")


@dataclass(frozen=True)
class CeresRun:
    """One run of the program: its JSON summary, the adjusted nodes and attitude sigmas."""

    summary: dict[str, object]
    nodes: F64
    attitude_sigma: F64
    wall_s: float


def run(
    exe: Path,
    problem: Path,
    n_nodes: int,
    solver: str,
    threads: int,
    *,
    extra: tuple[str, ...] = (),
    covariance: bool = False,
    timeout: float | None = None,
) -> CeresRun:
    """Run ``linescan_ba`` on a problem file (see the module doc for the options).

    Raises:
        RuntimeError: When the program fails.
    """
    import time

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "nodes.bin"
        cmd = [str(exe), "--problem", str(problem), "--out", str(out)]
        cmd += ["--solver", solver, "--threads", str(threads), *extra]
        if covariance:
            cmd.append("--covariance")
        t0 = time.perf_counter()
        env = dict(os.environ)
        for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
            env[var] = str(threads)  # any BLAS under Ceres: the same thread count
        proc = subprocess.run(
            cmd, capture_output=True, text=True, check=False, timeout=timeout, env=env
        )
        wall = time.perf_counter() - t0
        if proc.returncode != 0 or not out.is_file():
            raise RuntimeError(f"linescan_ba failed ({proc.returncode}): {proc.stderr.strip()}")
        raw = np.fromfile(out, "<f8")
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    return CeresRun(summary, raw[: 6 * n_nodes].reshape(n_nodes, 6), raw[6 * n_nodes :], wall)
