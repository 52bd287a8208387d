"""How far the true camera lies from anything the estimated camera model can represent.

:func:`best_fit_residuals` fits the *initial* camera's model (the native line-scan
model with the initial camera's node spacing, every node's attitude free and its
position loosely weighted (1 km), the interior orientation ``x0, y0, f`` per CCD loosely
weighted (0.1 mm, 10 mm): the most general native parameterisation the adjustment
offers) to exact synthetic observations of the *truth*: a grid of image points of every
CCD, each with the ground point where its true ray meets a level surface. The residuals
of that best fit are the part of the truth the model cannot represent: no run of the
pipeline can get below them, whatever the matcher.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["best_fit_residuals"]


def best_fit_residuals(
    truth: Any,
    initial: Any,
    *,
    n_lines: int = 97,
    n_samples: int = 17,
    height_m: float = 0.0,
) -> dict[str, Any]:
    """Fit the initial camera's model to the truth; residuals of the best fit.

    Args:
        truth: The true :class:`~planetref.camera.linescan.LineScanCamera`.
        initial: The initial camera (its model and node spacing are fitted).
        n_lines: Grid lines per CCD (evenly spread over the image, pixel centres).
        n_samples: Grid samples per CCD.
        height_m: Height of the level surface (m above the body).

    Returns:
        ``rms_px``, ``max_px`` (over all points) and ``ccds``: per CCD ``rms_px`` and
        ``max_px`` of the residual length, and the fitted camera under ``camera``.
    """
    from planetref.adjust import Network, adjust

    lines_l, samples_l, ccd_l, xyz_l = [], [], [], []
    for k, name in enumerate(truth.ccd_names):
        nl, ns = truth.image_size(name)
        gl = (np.floor(np.linspace(0, nl - 1, n_lines)) + 0.5).astype(np.float64)
        gs = (np.floor(np.linspace(0, ns - 1, n_samples)) + 0.5).astype(np.float64)
        ll, ss = (a.ravel() for a in np.meshgrid(gl, gs, indexing="ij"))
        xyz_l.append(truth.image_to_ground(ll, ss, height_m, ccd=name))
        lines_l.append(ll)
        samples_l.append(ss)
        ccd_l.append(np.full(len(ll), k, dtype=np.intp))
    line = np.concatenate(lines_l)
    sample = np.concatenate(samples_l)
    ccd = np.concatenate(ccd_l)
    xyz = np.concatenate(xyz_l)
    m = len(line)
    net = Network(
        cameras=(initial,),
        camera_ids=("strip",),
        point_ids=np.array([f"p{i}" for i in range(m)]),
        point_xyz=xyz,
        point_sigma_m=np.zeros((m, 3)),
        point_kind=np.array(["mcp"] * m),
        obs_camera=np.zeros(m, dtype=np.intp),
        obs_ccd=ccd,
        obs_point=np.arange(m),
        obs_line=line,
        obs_sample=sample,
        obs_sigma_px=np.ones((m, 2)),
        obs_check=np.zeros(m, dtype=bool),
        obs_ids=np.array([str(i) for i in range(m)]),
    )
    cfg = {
        "linescan": {
            "position": {"mode": "weighted", "sigma_m": 1000.0},
            "attitude": {"mode": "free"},
            "interior": {
                "mode": "weighted",
                "scope": "ccd",
                "sigma_principal_point_mm": 0.1,
                "sigma_focal_length_mm": 10.0,
            },
            "weak_nodes": "smooth",
            "ccd_placement": {"mode": "weighted", "sigma_offset_mm": 0.1, "sigma_angle_rad": 0.01},
        },
        "outliers": {"enabled": False},
        # A plain least-squares fit: exact observations carry no noise to estimate.
        "variance": {"enabled": False},
        "solver": {"loss": "linear", "max_iterations": 30},
    }
    result = adjust(net, cfg)
    fitted = result.cameras["strip"]
    out: dict[str, Any] = {"ccds": {}}
    all_res = []
    for k, name in enumerate(truth.ccd_names):
        sel = ccd == k
        p = fitted.ground_to_image(xyz[sel], ccd=name)
        r = np.hypot(p.line - line[sel], p.sample - sample[sel])
        all_res.append(r)
        out["ccds"][name] = {"rms_px": float(np.sqrt(np.mean(r**2))), "max_px": float(r.max())}
    r = np.concatenate(all_res)
    out["rms_px"] = float(np.sqrt(np.mean(r**2)))
    out["max_px"] = float(r.max())
    out["camera"] = fitted
    return out
