"""The exterior orientation of a CSM line-scan ISD as usgscsm samples it in time.

:class:`CsmEphemeris` holds the tables usgscsm builds from an ISD and interpolates:

* **Positions**: the ISD's positions/velocities (km, km/s, J2000) resampled to
  ``max(n, 25)`` evenly spaced epochs by a cubic Hermite fit that uses the velocities
  (a natural cubic spline when there are none), rotated to body-fixed with
  ``body_rotation`` (velocity including the ``-omega x r`` term), in metres; interpolated
  by 8th-order Lagrange (4th with platform flag 0).
* **Pointing**: sensor -> body quaternions on an evenly spaced grid (SLERP), interpolated
  by Lagrange on the components and normalised.
* **Time**: the ``line_scan_rate`` table (usgscsm's ``getImageTime``).

Times are seconds relative to ``center_ephemeris_time``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planetref.arrays import F64
from planetref.camera.csm.interpolation import hermite, lagrange, natural_spline
from planetref.camera.csm.isd import J2000, MIN_EPHEMERIS_NODES, CsmIsd
from planetref.camera.csm.orientation import AleOrientations, qmatrix

__all__ = ["CsmEphemeris"]


@dataclass(frozen=True, eq=False)
class CsmEphemeris:
    """Evenly resampled position and pointing tables and the line -> time table.

    Attributes:
        t0_position: Time of the first position node (s).
        dt_position: Spacing of the position nodes (s).
        positions: Body-fixed sensor positions (m), ``(N, 3)``.
        velocities: Body-fixed sensor velocities (m/s), ``(N, 3)``.
        t0_pointing: Time of the first quaternion node (s).
        dt_pointing: Spacing of the quaternion nodes (s).
        quaternions: Sensor -> body quaternions, ``(K, 4)``.
        order: Lagrange order of the positions (8, or 4 with platform flag 0).
        pointing_order: Lagrange order of the quaternions.
        rate_lines: First line of each ``line_scan_rate`` row.
        rate_times: Start time of each row (s).
        rate_rates: Seconds per line of each row.
    """

    t0_position: float
    dt_position: float
    positions: F64
    velocities: F64
    t0_pointing: float
    dt_pointing: float
    quaternions: F64
    order: int
    pointing_order: int
    rate_lines: F64
    rate_times: F64
    rate_rates: F64

    @classmethod
    def from_isd(cls, isd: CsmIsd) -> CsmEphemeris:
        """The tables usgscsm builds from a checked ISD."""
        center = isd.center_ephemeris_time
        body = AleOrientations.from_isd(isd.body_rotation)
        body_frame = isd.body_frame
        # Positions: resample evenly to >= 25 epochs (Hermite with the velocities),
        # rotate to body-fixed with the omega x r velocity term, km -> m.
        ip = isd.instrument_position
        times = np.asarray(ip.times)
        n = max(len(times), MIN_EPHEMERIS_NODES)
        step = (times[-1] - times[0]) / (n - 1)
        grid = times[0] + step * np.arange(n)
        vel_in = ip.velocities_km_s
        if vel_in is not None and np.any(vel_in != 0):
            pos, vel = hermite(times, np.asarray(ip.positions_km), np.asarray(vel_in), grid)
        else:
            pos = natural_spline(times, np.asarray(ip.positions_km), grid)
            vel = (
                np.zeros_like(pos)
                if vel_in is None
                else natural_spline(times, np.asarray(vel_in), grid)
            )
        if ip.reference_frame == J2000 or ip.reference_frame != body_frame:
            pos, vel = body.rotate_states(grid, pos, vel)
        # Pointing: sensor -> body on the union of the time grids, resampled by SLERP.
        pointing = AleOrientations.from_isd(isd.instrument_pointing)
        if (
            isd.instrument_pointing.reference_frame == J2000
            or isd.instrument_pointing.reference_frame != body_frame
        ):
            sensor_to_body = body.compose(pointing.inverse())
        else:
            sensor_to_body = pointing.inverse()
        qt = sensor_to_body.times
        qstep = (qt[-1] - qt[0]) / (len(qt) - 1) if len(qt) > 1 else 1.0
        qgrid = qt[0] + qstep * np.arange(max(len(qt), 2))
        q = sensor_to_body.interpolate(qgrid)
        q = q / np.linalg.norm(q, axis=1, keepdims=True)
        order = 8 if isd.platform_flag else 4
        return cls(
            t0_position=float(times[0] - center),
            dt_position=float(step),
            positions=pos * 1000.0,
            velocities=vel * 1000.0,
            t0_pointing=float(qt[0] - center),
            dt_pointing=float(qstep),
            # usgscsm stores [x, y, z, w]; Lagrange runs on the components in any order.
            quaternions=q,
            order=order,
            pointing_order=4 if (len(q) * 4 < 6 and order == 8) else order,
            rate_lines=np.asarray(isd.line_scan_rate[:, 0]),
            rate_times=np.asarray(isd.line_scan_rate[:, 1]),
            rate_rates=np.asarray(isd.line_scan_rate[:, 2]),
        )

    def image_time(self, lines: F64) -> F64:
        """Acquisition times (s) of 1-D line coordinates (usgscsm's ``getImageTime``)."""
        k = np.clip(np.searchsorted(self.rate_lines, lines, side="right") - 1, 0, None)
        return self.rate_times[k] + self.rate_rates[k] * (lines - self.rate_lines[k] + 0.5)

    def duration(self, n_lines: int) -> float:
        """Seconds from the start of line 0 to the end of line ``n_lines - 1``."""
        return float(
            self.rate_times[-1]
            - self.rate_times[0]
            + self.rate_rates[-1] * (n_lines - self.rate_lines[-1])
        )

    def position(self, t: F64) -> F64:
        """Body-fixed sensor positions (m) at times ``t``, ``(M, 3)``."""
        return lagrange(self.positions, self.t0_position, self.dt_position, t, self.order)

    def velocity(self, t: F64) -> F64:
        """Body-fixed sensor velocities (m/s) at times ``t``, ``(M, 3)``."""
        return lagrange(self.velocities, self.t0_position, self.dt_position, t, self.order)

    def rotation(self, t: F64) -> F64:
        """Sensor -> body rotation matrices at times ``t``, ``(M, 3, 3)``."""
        q = lagrange(self.quaternions, self.t0_pointing, self.dt_pointing, t, self.pointing_order)
        return qmatrix(q / np.linalg.norm(q, axis=1, keepdims=True))

    def coverage_problems(self, n_lines: int) -> list[str]:
        """Jumps in the line -> time table and image times outside the ephemeris.

        usgscsm silently extrapolates there (linearly, from the last interval), which is
        only good for a few lines.
        """
        rate = np.column_stack([self.rate_lines, self.rate_times, self.rate_rates])
        problems = []
        ends = rate[:-1, 1] + rate[:-1, 2] * (rate[1:, 0] - rate[:-1, 0])
        for k in np.flatnonzero(np.abs(rate[1:, 1] - ends) > 2.0 * rate[1:, 2]):
            problems.append(
                f"line_scan_rate row {k + 1} starts at {rate[k + 1, 1]:+.3f} s "
                f"but row {k} ends at {ends[k]:+.3f} s"
            )
        t0, t1 = self.image_time(np.array([0.0, float(n_lines)]))
        lo = max(self.t0_position, self.t0_pointing)
        hi = min(
            self.t0_position + self.dt_position * (len(self.positions) - 1),
            self.t0_pointing + self.dt_pointing * (len(self.quaternions) - 1),
        )
        slack = 2.0 * float(np.max(rate[:, 2]))
        if t0 < lo - slack or t1 > hi + slack:
            problems.append(
                f"the image spans {t0:+.3f}..{t1:+.3f} s but the ephemeris "
                f"covers only {lo:+.3f}..{hi:+.3f} s (relative to "
                "center_ephemeris_time): usgscsm extrapolates"
            )
        return problems
