"""usgscsm's per-image corrections of a CSM line-scan camera as adjustment unknowns."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.adjust.config import CsmParameters
from planetref.adjust.models.protocol import CoverageIssue, Evaluation, mode_and_sigma
from planetref.arrays import F64
from planetref.errors import AdjustmentError

__all__ = ["CsmParameterization"]

#: Line step (image lines) of the central differences of the detector offset along lines.
_LINE_STEP = 0.05
_CSM_TERMS = (
    # (block, indices into usgscsm's 16 parameters, names)
    ("position_offset", (0, 1, 2), ("in_track", "cross_track", "radial")),
    ("position_rate", (3, 4, 5), ("in_track_rate", "cross_track_rate", "radial_rate")),
    ("pointing_offset", (6, 7, 8), ("omega", "phi", "kappa")),
    ("pointing_rate", (9, 10, 11), ("omega_rate", "phi_rate", "kappa_rate")),
    ("pointing_acceleration", (12, 13, 14), ("omega_accel", "phi_accel", "kappa_accel")),
    ("focal_length", (15,), ("focal",)),
)


class CsmParameterization:
    """usgscsm's per-image corrections of a CSM line-scan camera.

    Local parameters are the (non-fixed) correction terms in usgscsm's own units (metres,
    see :class:`~planetref.camera.csm.CsmCorrection`); sigmas from the configuration's
    physical units are converted with the image's half duration ``T``, flying height
    ``H`` and half swath ``W``: pointing ``omega, phi`` ``sigma_m = sigma_rad H``, kappa
    ``sigma_rad W``; rates ``x T``; accelerations ``x T^2``; position rate
    ``sigma_m_s T``; focal ``sigma_mm W / f``. Partials differentiate the detector-line
    offset implicitly at the projected line (central differences of the offset in the
    correction terms, ground coordinates and line; see :meth:`_implicit_partials`): the
    same numbers as central differences of full ``ground_to_image`` solves, to ~1e-8
    px/m on the real CTX images, at one offset evaluation per perturbation.

    Args:
        camera_id: The image's id.
        camera: The initial camera (its existing correction is the starting point).
        config: Modes and sigmas of the correction blocks.
        fixed: Hold every parameter fixed.
    """

    def __init__(
        self, camera_id: str, camera: Any, config: CsmParameters, *, fixed: bool = False
    ) -> None:
        self.camera_id = camera_id
        self.camera = camera
        self.config = config
        t_half, height, swath = camera.half_time_s, camera.flying_height_m, camera.half_swath_m
        f_mm = float(camera.isd.focal_length_mm)
        scale = {
            "position_offset": (1.0, 1.0, 1.0),
            "position_rate": (t_half,) * 3,
            "pointing_offset": (height, height, swath),
            "pointing_rate": (height * t_half, height * t_half, swath * t_half),
            "pointing_acceleration": (height * t_half**2, height * t_half**2, swath * t_half**2),
            "focal_length": (swath / f_mm,),
        }
        sigma_field = {
            "position_offset": "sigma_m",
            "position_rate": "sigma_m_s",
            "pointing_offset": "sigma_rad",
            "pointing_rate": "sigma_rad_s",
            "pointing_acceleration": "sigma_rad_s2",
            "focal_length": "sigma_mm",
        }
        index, names, mode, sigma = [], [], [], []
        for block, idx, labels in _CSM_TERMS:
            cfg = getattr(config, block)
            if cfg.mode == "fixed" or fixed:
                continue
            raw_sigma = getattr(cfg, sigma_field[block])
            for j, lab, sc in zip(idx, labels, scale[block], strict=True):
                index.append(j)
                names.append(f"{lab}_m")
                m_, s_ = mode_and_sigma(
                    cfg.mode, None if raw_sigma is None else raw_sigma * sc, 1, False
                )
                mode.append(m_[0])
                sigma.append(s_[0])
        self._index = np.array(index, np.intp)
        self._base = camera.correction.as_array()
        self.names = tuple(names)
        self.units = tuple("m" for _ in names)
        self.x0 = self._base[self._index].copy()
        self.mode = np.array(mode, np.int8)
        self.sigma = np.array(sigma, np.float64)
        q = max(len(index), 1)
        cols = np.full((1, q), -1, np.intp)
        cols[0, : len(index)] = np.arange(len(index))
        self.pattern_columns = cols
        #: No linear pseudo-observations between the correction terms.
        self.constraints: tuple[F64, F64] | None = None
        self._cache: tuple[bytes, Any] | None = None

    def _camera(self, x: F64) -> Any:
        from planetref.camera.csm import CsmCorrection

        key = np.asarray(x, np.float64).tobytes()
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1]
        full = self._base.copy()
        full[self._index] = x
        cam = self.camera.with_correction(CsmCorrection.from_array(full))
        self._cache = (key, cam)
        return cam

    def _project(self, cam: Any, xyz: F64) -> tuple[F64, F64, NDArray[np.bool_]]:
        ip = cam.ground_to_image(xyz)
        return ip.line, ip.sample, ip.valid

    def evaluate(
        self,
        x: F64,
        xyz: F64,
        ccd: int,
        line_guess: F64,
        rate_guess: F64 | None = None,
        partials: bool = True,
    ) -> Evaluation:
        """Project into the image with central-difference partials.

        Args:
            x: Local parameters (usgscsm metres).
            xyz: Ground points (metres), ``(m, 3)``.
            ccd: Must be 0 (one CCD per CSM camera).
            line_guess: Unused (the CSM model finds its own starting lines).
            rate_guess: Unused.
            partials: ``False`` projects only.
        """
        x = np.asarray(x, np.float64)
        xyz = np.asarray(xyz, np.float64)
        m = len(xyz)
        line, samp, valid = self._project(self._camera(x), xyz)
        if not partials:
            line = np.where(valid, line, np.nan)
            samp = np.where(valid, samp, np.nan)
            return Evaluation(
                line, samp, valid, np.zeros(m, np.intp), np.empty((m, 2, 0)), np.empty((m, 2, 0))
            )
        q = self.pattern_columns.shape[1]
        d_params, d_ground, ok = self._implicit_partials(x, xyz, line, valid, q)
        valid &= ok
        bad = ~valid
        line = np.where(valid, line, np.nan)
        samp = np.where(valid, samp, np.nan)
        d_params[bad] = 0.0
        d_ground[bad] = 0.0
        return Evaluation(line, samp, valid, np.zeros(m, np.intp), d_params, d_ground)

    def _implicit_partials(
        self, x: F64, xyz: F64, line: F64, valid: NDArray[np.bool_], q: int
    ) -> tuple[F64, F64, NDArray[np.bool_]]:
        """Partials of (line, sample) by implicit differentiation at the projected lines.

        The image line ``l`` of a point solves ``g(l; p, X) = 0`` with ``g`` the
        detector-line offset (usgscsm's ``calcDetectorLineErr``), so
        ``dl/dp = -(dg/dp) / (dg/dl)`` and ``ds/dp = ds/dp|_l + ds/dl dl/dp``, all at the
        nominal line: one offset evaluation per perturbed parameter instead of a full
        ``ground_to_image`` (a secant search from scratch) each. ``dg/dp`` and ``ds/dp``
        are central differences with step ``fd_step_m`` (ground: ``fd_ground_step_m``);
        ``dg/dl``, ``ds/dl`` central differences of ``_LINE_STEP`` lines.

        Returns:
            ``(d_params (m, 2, q), d_ground (m, 2, 3), finite)``.
        """
        m = len(xyz)
        cam = self._camera(x)
        nl = float(cam.image_size()[0])
        at = np.where(valid, line, nl / 2.0)
        h, g, dl = self.config.fd_step_m, self.config.fd_ground_step_m, _LINE_STEP
        # Nominal camera, one call: the line +-dl and the six ground shifts +-g on X, Y, Z.
        shifts = np.concatenate([np.eye(3), -np.eye(3)]) * g
        pts = np.concatenate([xyz, xyz, (xyz[None, :, :] + shifts[:, None, :]).reshape(-1, 3)])
        lines = np.concatenate([at + dl, at - dl, np.tile(at, 6)])
        off, smp, _ = cam.detector_offset(lines, pts)
        off, smp = off.reshape(8, m), smp.reshape(8, m)
        with np.errstate(invalid="ignore", divide="ignore"):
            g_l = (off[0] - off[1]) / (2 * dl)
            s_l = (smp[0] - smp[1]) / (2 * dl)
            d_ground = np.empty((m, 2, 3))
            g_x = ((off[2:5] - off[5:8]) / (2 * g)).T
            d_ground[:, 0, :] = -g_x / g_l[:, None]
            d_ground[:, 1, :] = ((smp[2:5] - smp[5:8]) / (2 * g)).T + s_l[:, None] * d_ground[
                :, 0, :
            ]
            d_params = np.zeros((m, 2, q))
            for j in range(len(self._index)):
                xp, xm = x.copy(), x.copy()
                xp[j] += h
                xm[j] -= h
                op, sp_, _ = self._camera(xp).detector_offset(at, xyz)
                om, sm, _ = self._camera(xm).detector_offset(at, xyz)
                d_params[:, 0, j] = -((op - om) / (2 * h)) / g_l
                d_params[:, 1, j] = (sp_ - sm) / (2 * h) + s_l * d_params[:, 0, j]
        self._camera(x)  # leave the cache on the nominal parameters
        finite = np.all(np.isfinite(d_params), axis=(1, 2)) & np.all(
            np.isfinite(d_ground), axis=(1, 2)
        )
        return d_params, d_ground, finite

    def build(self, x: F64) -> Any:
        """The CSM camera with the correction ``x`` (other terms as initially)."""
        return self._camera(np.asarray(x, np.float64))

    def physical(self, x: F64) -> dict[str, float]:
        """The correction terms in physical units (m, m/s, rad, rad/s, rad/s², mm)."""
        cam = self.camera
        t_half, height, swath = cam.half_time_s, cam.flying_height_m, cam.half_swath_m
        f_mm = float(cam.isd.focal_length_mm)
        out: dict[str, float] = {}
        full = self._base.copy()
        full[self._index] = np.asarray(x, np.float64)
        for block, idx, labels in _CSM_TERMS:
            for j, lab in zip(idx, labels, strict=True):
                v = float(full[j])
                if block == "position_offset":
                    out[f"{lab}_m"] = v
                elif block == "position_rate":
                    out[f"{lab}_m_s"] = v / t_half
                elif block == "focal_length":
                    out["focal_length_correction_mm"] = -v * f_mm / swath
                else:
                    power = {"pointing_offset": 0, "pointing_rate": 1, "pointing_acceleration": 2}[
                        block
                    ]
                    lever = swath if lab.startswith("kappa") else height
                    unit = {0: "rad", 1: "rad_s", 2: "rad_s2"}[power]
                    out[f"{lab}_{unit}"] = v / (lever * t_half**power)
        return out

    def coverage(self, ccd: NDArray[np.intp], line: F64) -> list[CoverageIssue]:
        """The image as a whole needs as many observations as it has free terms."""
        free = np.flatnonzero(self.mode != 2)
        need = math.ceil(len(free) / 2) + 1 if free.size else 0
        if len(line) < need:
            return [
                CoverageIssue(
                    f"image {self.camera_id!r}", tuple(int(i) for i in free), len(line), need
                )
            ]
        return []

    def weaken(self, issues: list[CoverageIssue]) -> tuple[CsmParameterization, list[str]]:
        """Too few observations for an image's correction: always an error.

        Returns:
            ``(self, [])`` when there are no issues.

        Raises:
            AdjustmentError: Naming the image and the counts.
        """
        if not issues:
            return self, []
        i = issues[0]
        raise AdjustmentError(
            f"image {self.camera_id!r}: {i.count} observation(s) cannot "
            f"determine its {len(i.indices)} correction term(s) "
            f"{list(self.names)}; fix the image or add observations"
        )
