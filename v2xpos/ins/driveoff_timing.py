"""The IMU time offset from a drive-off, before the heading is set: the onset of motion aligned in time.

Why (docs/integrity.md, What is short): the GNSS models carry the time offset ``dt`` through their
first-order terms, ``p(t - dt) ~ p - v dt`` and ``v(t - dt) ~ v - a dt``. They hold while the
acceleration is nearly constant over the offset's uncertainty. A drive-off is the opposite: the
acceleration rises from 0 to 1-3 m/s^2 within about half a second, while the offset's prior sd is
0.3 s (``effects.DEFAULT_INITIAL_SD``). Linearised there, single GNSS epochs after the heading reset
moved the estimate by hundreds of ms and left it several sd from the truth with an sd of ~10 ms.

What: from a stop the filter runs with its heading open (``Initialization._try_align``) and, once
moving, uses no GNSS until the heading is set (``InsFilter.update_gnss``): the strapdown runs free
there. Its horizontal track since the stop (the antenna's: the IMU point's plus the change of
``C_nb l``, which turns with the car) is known in length and shape, only not in direction; so is
the GNSS antenna's. The two are the same plane curve turned by the strapdown's unknown heading
error ``theta``, the strapdown's on the IMU stamps, the receiver's on GPS time. The offset is the
shift that lays one onto the other:

    J(dt) = min_{d0, theta}  sum_k |p_gnss(t_k) - d0 - R(theta) p_ins(t_k - dt)|^2 / s_k^2
            +  (dt - dt_prior)^2 / sd_prior^2

over the GNSS epochs ``t_k`` of the drive-off, evaluated exactly on a grid of ``dt`` over the prior's
+-``GRID_HALF_WIDTH_SD`` sd (the strapdown is interpolated, not linearised, so the ramp's curvature is
used, not misread). ``d0`` takes up the error of the common anchor at the stop; the inner minimum is
the weighted orthogonal Procrustes problem in the plane, in closed form (``_procrustes_cost``;
Umeyama 1991, IEEE TPAMI 13(4), without the scale). Fitting the rotation, rather than projecting
each track on its own direction of travel, keeps a drive-off that curves (out of a parking space)
right: with the projections, on a circle of 6 m (full lock) the normalised error's RMS was 1.6
(mean -1.2) and on 4 m 3.3 (mean -3.1) over simulated drive-offs, the two chords pointing along
different parts of the curve (``test_a_drive_off_that_curves_gives_the_time_offset``). The estimate is the
grid minimum refined by a parabola, its variance ``2 / J''`` (J is a chi-square, minus twice the log
posterior: the Laplace approximation; Bar-Shalom, Li & Kirubarajan 2001 sec. 2.7). ``s_k`` is the
receiver's sd along the track with the strapdown's own drift added, ``(b t^2 / 2)`` for an
accelerometer bias of the filter's current sd ``b`` (Groves 2013 sec. 5.7 for the growth of a free
inertial solution). This is the classical time alignment of two records of the same motion by the
shift that matches them best (e.g. Li & Mourikis 2014, sec. 1, for its place among temporal
calibration methods), done once, where the filter's own linear model cannot do it.

In the filter (``Initialization._heading_reset``, ``_finish_drive_off_alignment``): the heading is
set at the first epoch fast enough for a course, as before, so that an outage right after a
drive-off still has it. The strapdown's record then runs on (its frame turned with the heading,
``turn``) until it has passed every shift on the grid for the epochs of the open-heading phase
(``needed_wait_s``: about a second at the 0.3 s prior). Until then the GNSS models carry the time
offset as noise, not as columns (``_timing_as_noise``); at the first epoch after the wait the
alignment sets the offset and its sd, and the heading, position and velocity are taken again from
that epoch at the filter's new label. The other states keep what the stop taught them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

GRID_HALF_WIDTH_SD = 3.0          # the grid spans the prior +- this many sd
GRID_STEP_S = 0.002
MIN_MOVING_EPOCHS = 3             # epochs after the onset needed to say anything
MAX_WINDOW_S = 10.0               # a stop and drive-off longer than this is not kept whole


@dataclass(frozen=True)
class TimeAlignment:
    """The result: the offset [s] to set, its sd [s], and what it was made of."""
    offset_s: float
    sd_s: float
    epochs: int
    moving_epochs: int


class DriveOffTimer:
    """Collects the free strapdown's and the receiver's horizontal tracks from the stop through the
    drive-off (module docstring) and aligns them in time.

    ``note_ins`` takes, at an IMU stamp, the strapdown's own horizontal velocity change over the
    chunk and the horizontal part of the lever arm ``C_nb l`` (north/east in the strapdown's frame,
    whose heading is arbitrary until the heading reset); ``note_gnss`` the antenna's position
    (north/east metres of a fixed origin) at a GPS time with its horizontal sd and the receiver's
    speed. A receiver speed at rest after motion starts a new record (a new drive-off)."""

    def __init__(self, static_max_speed_mps: float):
        self.static_max_speed_mps = float(static_max_speed_mps)
        self.clear()

    def clear(self) -> None:
        self._ins: list[tuple[float, ...]] = []
        self._gnss: list[tuple[float, float, float, float, float]] = []

    def note_ins(self, stamp_s: float, free_dv_ne_mps: np.ndarray, lever_ne_m: np.ndarray) -> None:
        """The strapdown's own horizontal velocity change (north, east; every update's correction
        taken out) over the chunk ending at ``stamp_s``, and the lever arm's horizontal part then:
        the antenna moves by its change too (a car pitches when it accelerates)."""
        self._ins.append((float(stamp_s), float(free_dv_ne_mps[0]), float(free_dv_ne_mps[1]),
                          float(lever_ne_m[0]), float(lever_ne_m[1])))
        while self._ins and self._ins[0][0] < stamp_s - MAX_WINDOW_S - 2.0:
            self._ins.pop(0)

    def note_gnss(self, t_s: float, ne_m: np.ndarray, sd_h_m: float, speed_mps: float) -> None:
        if speed_mps <= self.static_max_speed_mps and self._gnss and self._gnss[-1][4] > self.static_max_speed_mps:
            self._gnss.clear()            # stopped again: a new drive-off starts from here
        self._gnss.append((float(t_s), float(ne_m[0]), float(ne_m[1]), float(sd_h_m), float(speed_mps)))
        while len(self._gnss) > 2 and self._gnss[0][0] < t_s - MAX_WINDOW_S:
            self._gnss.pop(0)

    def starts_at_rest(self) -> bool:
        """Whether the receiver's record starts at a stop (the alignment's anchor)."""
        return bool(self._gnss) and self._gnss[0][4] <= self.static_max_speed_mps

    @staticmethod
    def needed_wait_s(prior_sd_s: float) -> float:
        """How long after the first fast epoch the alignment waits for the strapdown: the grid's
        half width."""
        return GRID_HALF_WIDTH_SD * float(prior_sd_s)

    def turn(self, turn_ne: np.ndarray) -> None:
        """The strapdown's frame turned about down (``Initialization._turn_about_down``): the
        recorded velocity changes are turned with it, so that the track stays in one frame."""
        r = np.asarray(turn_ne, float)[:2, :2]
        self._ins = [(t, *(r @ np.array([n, e])), *(r @ np.array([ln, le]))) for t, n, e, ln, le in self._ins]

    @staticmethod
    def _ins_at(track: tuple, stamps_s: np.ndarray) -> np.ndarray | None:
        """The free strapdown's displacement at ``stamps_s`` (cubic Hermite between the chunk ends'
        positions and velocities); None when any stamp is outside the track."""
        t, p, v = track
        if stamps_s.min() < t[0] or stamps_s.max() > t[-1]:
            return None
        k = np.clip(np.searchsorted(t, stamps_s, side="right") - 1, 0, len(t) - 2)
        h = t[k + 1] - t[k]
        s = np.where(h > 0, (stamps_s - t[k]) / np.where(h > 0, h, 1.0), 0.0)
        h00, h10 = 2 * s ** 3 - 3 * s ** 2 + 1, s ** 3 - 2 * s ** 2 + s
        h01, h11 = -2 * s ** 3 + 3 * s ** 2, s ** 3 - s ** 2
        if p.ndim == 2:
            h00, h10, h01, h11, h = (x[:, None] for x in (h00, h10, h01, h11, h))
        return h00 * p[k] + h10 * h * v[k] + h01 * p[k + 1] + h11 * h * v[k + 1]

    @staticmethod
    def _procrustes_cost(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> float:
        """``min_{d0, theta} sum_k w_k |a_k - d0 - R(theta) b_k|^2`` for plane points (n, 2): with
        the weighted centroids removed (``A``, ``B``) the best rotation makes ``R B`` parallel to
        ``A`` on (weighted) average, and the minimum is ``sum w |A|^2 + sum w |B|^2 - 2 |sum w
        (B . A, B x A)|``."""
        wn = w / w.sum()
        A = a - wn @ a
        B = b - wn @ b
        dot = float(w @ np.einsum("ij,ij->i", B, A))
        cross = float(w @ (B[:, 0] * A[:, 1] - B[:, 1] * A[:, 0]))
        return float(w @ np.einsum("ij,ij->i", A, A) + w @ np.einsum("ij,ij->i", B, B)) - 2.0 * math.hypot(dot, cross)

    def align(self, prior_offset_s: float, prior_sd_s: float, accel_bias_sd_mps2: float) -> TimeAlignment | None:
        """The time offset from the drive-off (module docstring), or None when the record does not
        hold a stop followed by enough motion, or does not cover the grid."""
        if len(self._gnss) < MIN_MOVING_EPOCHS + 2 or len(self._ins) < 4 or not (prior_sd_s > 0):
            return None
        half = self.needed_wait_s(prior_sd_s)
        grid = prior_offset_s + np.arange(-half, half + GRID_STEP_S / 2, GRID_STEP_S)
        g = np.asarray(self._gnss)
        g = g[g[:, 0] <= self._ins[-1][0] + grid[0]]     # epochs the strapdown has passed at every shift
        if len(g) < MIN_MOVING_EPOCHS + 2:
            return None
        rest = g[:, 4] <= self.static_max_speed_mps
        if not rest[0]:
            return None                   # the record does not start at a stop
        onset = int(np.argmin(rest)) if not rest.all() else len(g)
        moving = len(g) - onset
        if moving < MIN_MOVING_EPOCHS:
            return None
        t_onset = g[onset, 0]
        keep = g[:, 0] >= t_onset - 1.0   # the last second at rest anchors the curve
        g = g[keep]
        anchor = g[g[:, 4] <= self.static_max_speed_mps, 1:3].mean(axis=0)
        disp = g[:, 1:3] - anchor
        # the free strapdown from rest: integrated from a stamp at which the vehicle stands still for
        # every shift on the grid (the receiver's last second at rest, moved by the largest shift)
        ins = np.asarray(self._ins)
        start = int(np.searchsorted(ins[:, 0], g[0, 0] - grid[-1], side="right")) - 1
        if start < 0:
            return None
        ins = ins[start:]
        v = np.vstack([np.zeros(2), np.cumsum(ins[1:, 1:3], axis=0)])
        dt = np.diff(ins[:, 0])
        p = np.vstack([np.zeros(2), np.cumsum(0.5 * (v[1:] + v[:-1]) * dt[:, None], axis=0)])
        lever = ins[:, 3:5] - ins[0, 3:5]             # the antenna, not the IMU point, is compared
        p = p + lever
        v = v + np.gradient(lever, ins[:, 0], axis=0)
        if float(np.linalg.norm(p[-1])) < 1e-3:
            return None
        track = (ins[:, 0], p, v)
        t_rel = np.maximum(g[:, 0] - t_onset, 0.0)
        # per horizontal axis: the receiver's sd and the free strapdown's drift
        var = g[:, 3] ** 2 + (0.5 * accel_bias_sd_mps2 * t_rel ** 2) ** 2
        w = 1.0 / var
        cost = np.full(len(grid), np.inf)
        for n, dt in enumerate(grid):
            p_ins = self._ins_at(track, g[:, 0] - dt)
            if p_ins is None:
                continue
            cost[n] = self._procrustes_cost(disp, p_ins, w) + ((dt - prior_offset_s) / prior_sd_s) ** 2
        if not np.isfinite(cost).all():
            return None                   # the strapdown has not run past every shift yet
        n = int(np.argmin(cost))
        if n == 0 or n == len(grid) - 1:
            return None                   # the minimum is at the grid's edge: no confident answer
        c_m, c_0, c_p = cost[n - 1], cost[n], cost[n + 1]
        curv = (c_p - 2 * c_0 + c_m) / GRID_STEP_S ** 2
        if not curv > 0:
            return None
        shift = 0.5 * (c_m - c_p) / (c_p - 2 * c_0 + c_m) * GRID_STEP_S
        sd = math.sqrt(2.0 / curv)
        return TimeAlignment(float(grid[n] + shift), min(sd, prior_sd_s), int(len(g)), int(moving))
