"""Fixed-interval smoothing of ``InsFilter``: a Rauch-Tung-Striebel backward pass over the
closed-loop error-state filter, with the same error states the services estimate.

Forward pass (``StepRecorder``, attached as ``InsFilter.recorder``). The filter tells it
(``filter.py``) of

* every covariance propagation (``_flush_covariance``): the transition ``Phi`` of the chunk, the
  process noise ``q_c dt`` and the covariance ``P+`` it propagates -- this closes node i and opens
  node i+1 at the new time;
* every correction ``dx`` fed back into the nominal state (``_update``): summed per node;
* every reset that rewrites P and moves the nominal state (start, position and heading resets,
  lever-arm exclusion, ``_smoothing_boundary``) and every propagation while the heading is still
  open (``_decouple_yaw`` rewrites P then): the current segment ends there;
* every reset that gives some states a fresh estimate decoupled from the rest
  (``_update_static_calibration``: the gyro biases reset to a stop's estimate when it refutes
  them): a transition ``P_after = T P_before T^T + Q`` (``reset_transition``: the decoupled rows of
  T zero, Q their new covariance), recorded as a node at the same time.

Error convention (``ekf``): ``dx = estimate - truth``. The filter is closed loop: after the updates
of node i its nominal state is ``x_i+`` and its error estimate is 0 with covariance ``P_i+``; the
strapdown carries ``x_i+`` to the next node's predicted nominal ``x_{i+1}-`` and the error as
``dx_{i+1}- = Phi_i dx_i+ + w``, ``P_{i+1}- = Phi_i (P_i+ + Q/2) Phi_i^T + Q/2``
(``ekf.propagate_with_transition``). The updates at node i+1 estimate the error ``c_{i+1}`` (the
sum of the corrections fed back) and move the nominal: ``x_{i+1}+ = x_{i+1}- - c_{i+1}``, so an
error relative to the post-update nominal is the one relative to the predicted nominal minus
``c_{i+1}``. Written in these coordinates the Rauch-Tung-Striebel recursion (Rauch, Tung &
Striebel 1965; Groves 2013 sec. 3.4.2; Särkkä 2013 ch. 8, Theorem 8.2) for the smoothed error
``e_i`` (estimate minus truth, relative to ``x_i+``) is::

    e_N = 0,   P_N^s = P_N+                          (last node of the segment: the filter's)
    e_{i+1}^- = e_{i+1} + c_{i+1}                    (relative to the predicted nominal x_{i+1}-)
    G_i = P_i+ Phi_i^T (P_{i+1}-)^-1
    e_i = G_i e_{i+1}^-                              (the filter's own error estimate there is 0)
    P_i^s = P_i+ + G_i (P_{i+1}^s - P_{i+1}-) G_i^T

-- the form of Shin 2005 (ch. 5, the closed-loop RTS of a loosely coupled INS/GPS) and of
KF-GINS's post-processing: the predicted error is 0 because the feedback already moved the
nominal, and the corrections re-enter as the difference between the two nominals. The smoothed
state at node i is ``x_i+`` corrected by ``e_i`` as the filter corrects (``InsFilter._apply``);
its covariance is ``P_i^s``. Covariances do not depend on the nominal, so ``P^s`` needs no
feedback term. A decoupling reset is a step of the same recursion with ``Phi = T`` and
``P- = T P+ T^T + Q``: what the reset states were before it is not informed by what comes after,
everything else is (their new error is independent of the old, so the jump of their nominal
value does not enter). A reset that moves the whole state and replaces the covariance (a start, a
position or heading reset taken from a fix, an exclusion that takes another solution) has no
such transition:
it is a segment boundary, each segment is smoothed on its own, and what comes before a boundary is
not corrected by what comes after it.

Between nodes (a "tap": an output the caller wants smoothed, e.g. a GNSS epoch or every IMU sample
of a service) the nominal is the strapdown from ``x_i+``; the smoothed error there is interpolated
linearly in time between ``e_i`` and ``e_{i+1}^-`` (both relative to the nominal the tap saw), the
covariance likewise between ``P_i^s`` and ``P_{i+1}^s``. Node spacing is one IMU chunk
(``cov_every`` samples) or less, where the errors change by far less than their sd. A tap taken at
a node's time between two of its updates adds the corrections still to come at that node. The
caller gives each tap the rows J of what it reports (``reported_rows``, ``antenna_rows``); the
pass returns ``e`` (the full error, for effect states and biases), ``J e`` and ``J P^s J^T``.

Storage (``StepRecorder``, per node): ``P+`` (float32: the standard deviations in float64 and
the Cholesky factor of the correlation matrix in float32, lower triangle -- the decoded matrix is
positive semi-definite whatever the rounding; float64: the upper triangle), the rows of
``Phi - I`` that the error dynamics can fill (``transition_support``; the rest of Phi is the
identity, checked at every node), ``q_c dt`` (float32) and the summed correction (float64).
``P-`` and ``G`` are recomputed in the backward pass. With 27 states that is about 3.9 kB a node
(float32), at about 20 nodes per second 280 MB for an hour. Storage grows in fixed blocks
(``BLOCK_NODES``), so no array is ever copied to grow. docs/smoothing.md has the rest.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.linalg.lapack import dpotrf, dpotrs

from v2xpos import geo
from v2xpos.rotation import dcm_from_euler, euler_from_dcm, exp_so3, skew
from v2xpos.types import FixStatus, NavState

from .ekf import ATT, BASE_STATES, POS, VEL, propagate_with_transition
from .observers import FilterObserver
from .reported import correlations, reported_jacobian

BLOCK_NODES = 4096
"""Nodes (and taps) per storage block."""
CHOLESKY_JITTER = (0.0, 1e-12, 1e-10, 1e-8, 1e-6)
"""Relative diagonal loads tried, in order, when a correlation matrix is not numerically positive
definite for its float32 Cholesky factor (the decoded covariance then differs by that share of
each variance)."""
PRECISIONS = ("float32", "float64")


class _Blocks:
    """A growable array of fixed-width rows stored in blocks of ``BLOCK_NODES`` rows (growing never
    copies what is stored; indexing is by row)."""

    def __init__(self, width: int, dtype, block: int = BLOCK_NODES):
        self.width, self.dtype, self.block = int(width), np.dtype(dtype), int(block)
        self.blocks: list[np.ndarray] = []

    def row(self, i: int) -> np.ndarray:
        b, k = divmod(i, self.block)
        if b >= len(self.blocks):
            self.blocks.append(np.zeros((self.block, self.width), self.dtype))
        return self.blocks[b][k]

    @property
    def nbytes(self) -> int:
        return sum(b.nbytes for b in self.blocks)


class CovarianceCodec:
    """Packs a symmetric covariance for storage (module docstring): ``float32`` -- standard deviations
    in float64 (``scale``) and the Cholesky factor of the correlation matrix, lower triangle, in
    float32 (``packed``; the decoded matrix is positive semi-definite by construction);
    ``float64`` -- the upper triangle as it is (no scale)."""

    def __init__(self, n: int, precision: str = "float32"):
        if precision not in PRECISIONS:
            raise ValueError(f"precision {precision!r} not one of {PRECISIONS}")
        self.n, self.precision = n, precision
        self.factor = precision == "float32"
        r, c = np.tril_indices(n) if self.factor else np.triu_indices(n)
        self.flat = r * n + c
        self.width = len(self.flat)
        self.scale_width = n if self.factor else 0
        self.dtype = np.float32 if self.factor else np.float64
        self._eye = np.eye(n)

    def encode(self, P: np.ndarray, scale_out: np.ndarray, packed_out: np.ndarray) -> None:
        if not self.factor:
            packed_out[:] = np.take(P, self.flat)
            return
        sd = np.sqrt(np.maximum(P.diagonal(), 0.0))
        inv = 1.0 / np.where(sd > 0.0, sd, 1.0)
        R = P * np.outer(inv, inv)
        np.fill_diagonal(R, 1.0)
        for load in CHOLESKY_JITTER:
            A = R if load == 0.0 else (R + load * self._eye) / (1.0 + load)
            L, info = dpotrf(A, lower=1, clean=1)
            if info == 0:
                break
        else:
            w, V = np.linalg.eigh(R)
            L, info = dpotrf((V * np.maximum(w, 1e-6)) @ V.T, lower=1, clean=1)
        scale_out[:] = sd
        packed_out[:] = np.take(L, self.flat)

    def decode(self, scale: np.ndarray, packed: np.ndarray) -> np.ndarray:
        n = self.n
        M = np.zeros(n * n)
        M[self.flat] = packed
        M = M.reshape(n, n)
        if not self.factor:
            return M + np.triu(M, 1).T
        R = M @ M.T
        R *= scale[:, None]
        R *= scale
        return R


def transition_support(layout) -> tuple[np.ndarray, np.ndarray]:
    """(rows, columns) of the error-state transition that can differ from the identity. Rows: the
    15 base states (the strapdown's F, ``mechanization``) and the IMU time offset when the clock
    drift drives it (``InsFilter._flush_covariance``); every effect is otherwise a random constant
    or random walk. Columns: the base states, the gyro and accelerometer scales (``kernel_index``)
    and the clock drift."""
    rows, cols = list(range(BASE_STATES)), list(range(BASE_STATES))
    i_dt, i_dr = layout.at("imu_time_offset"), layout.at("imu_clock_drift")
    if i_dt >= 0 and i_dr >= 0:
        rows.append(i_dt)
        cols.append(i_dr)
    for name in ("gyro_scale", "accel_scale"):
        i = layout.at(name)
        if i >= 0:
            cols += [i, i + 1, i + 2]
    return np.asarray(rows, dtype=np.int64), np.asarray(sorted(cols), dtype=np.int64)


@dataclass
class SmoothedTaps:
    """What the backward pass gives for each tap k (in the order taken): ``smoothed[k]`` (False when
    the tap lies outside a smoothed interval: before a segment's first or after its last node; the
    caller keeps its forward values there), the smoothed error ``dx[k]`` (estimate minus truth,
    relative to the nominal state the tap saw, n), its standard deviations ``sd[k]`` (n), ``y[k] =
    J_k dx[k]`` (m) and ``cov[k] = J_k P^s J_k^T`` (m x m). ``y`` in float64, the others in the
    recorder's storage precision (an hour of taps at 10 Hz holds 36,000 x 200 numbers)."""
    smoothed: np.ndarray
    dx: np.ndarray
    sd: np.ndarray
    y: np.ndarray
    cov: np.ndarray


def smoother_gain(P_plus: np.ndarray, Phi: np.ndarray, P_minus: np.ndarray) -> np.ndarray:
    """G = P+ Phi^T (P-)^-1 by a Cholesky solve of P- over the states that have variance (a state
    with none -- an effect declared exact -- has no covariance with anything: its column of G is 0);
    a P- that is not numerically positive definite falls back to its pseudo-inverse."""
    B = Phi @ P_plus
    act = P_minus.diagonal() > 0.0
    ix = None if act.all() else np.flatnonzero(act)
    A = P_minus if ix is None else P_minus[np.ix_(ix, ix)]
    c, info = dpotrf(A, lower=1, clean=0)
    if info == 0:
        X, info = dpotrs(c, B if ix is None else B[ix], lower=1)
    if info != 0:
        return (np.linalg.pinv(P_minus, hermitian=True) @ B).T
    if ix is None:
        return X.T
    G = np.zeros_like(P_plus)
    G[:, ix] = X.T
    return G


RESET_PSD_TOLERANCE = 1e-9
"""Least eigenvalue of the correlation-scaled Q of a reset (``reset_transition``) still taken as
positive semi-definite (rounding of the rewritten covariance)."""


def reset_transition(P_before: np.ndarray, P_after: np.ndarray,
                     decoupled: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(T, Q) with ``P_after = T P_before T^T + Q``, Q positive semi-definite, for a rewrite of the
    covariance that gives the states ``decoupled`` a fresh estimate and covariance of their own
    (e.g. the gyro biases reset to a stop's estimate): T is the identity with those rows 0, Q the
    rest (their new covariance, and any variance added elsewhere). None when no such Q exists (the
    rewrite removed information from other states too: a boundary). The nominal value of a
    decoupled state may change with the rewrite (its new error is independent of the old one);
    any other must not."""
    n = P_after.shape[0]
    T = np.eye(n)
    T[decoupled, decoupled] = 0.0
    TP = P_before.copy()
    TP[decoupled, :] = 0.0
    TP[:, decoupled] = 0.0
    Q = P_after - TP
    Q = 0.5 * (Q + Q.T)
    d = np.sqrt(np.maximum(P_after.diagonal(), 0.0))
    inv = 1.0 / np.where(d > 0.0, d, 1.0)
    if np.linalg.eigvalsh(Q * np.outer(inv, inv)).min() < -RESET_PSD_TOLERANCE:
        return None
    return T, Q


class StepRecorder(FilterObserver):
    """Records what the backward pass needs (module docstring) and runs it (``smooth``).

    n: error states; support: the (rows, columns) of Phi that may differ from the identity
    (``transition_support``; None: all; a Phi with more is stored whole); tap_rows: m, the rows of every tap's J; precision: how P+ and Phi are stored
    (``CovarianceCodec``; Phi rows and q_c dt in float32 unless "float64").

    The filter calls ``propagate`` / ``correct`` / ``boundary`` (``InsFilter.recorder``); the
    same steps without a filter are ``step`` / ``correct`` / ``close`` (a linear test system).
    The caller adds taps (``tap``) while the filter runs, calls ``finish`` at the end and then
    ``smooth``.

    Per node two rows: ``lo`` (the storage precision) = [packed P+ | block of Phi - I | q_c dt] and
    ``hi`` (float64) = [time | scale of P+ | summed correction]; per tap ``tap_lo`` (float32) = J
    and ``tap_hi`` (float64) = [time | node | corrections at the node so far]."""

    def __init__(self, n: int, support: tuple | None = None, tap_rows: int = 9, precision: str = "float32"):
        self.n, self.m = int(n), int(tap_rows)
        self.codec = c = CovarianceCodec(self.n, precision)
        rows, cols = (np.arange(self.n), np.arange(self.n)) if support is None else support
        self._block = np.ix_(np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64))
        self._eye = np.eye(self.n)
        self._eye_block = self._eye[self._block]
        self._block_shape = self._eye_block.shape
        n_phi = self._eye_block.size
        self._lo = (slice(0, c.width), slice(c.width, c.width + n_phi), slice(c.width + n_phi, c.width + n_phi + n))
        self._hi = (slice(1, 1 + c.scale_width), slice(1 + c.scale_width, 1 + c.scale_width + n))
        self.lo = _Blocks(c.width + n_phi + n, c.dtype)
        self.hi = _Blocks(1 + c.scale_width + n, np.float64)
        self.phi_full: dict[int, np.ndarray] = {}
        self.resets: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.nodes = 0
        self._cur = -1
        self._cur_hi: np.ndarray | None = None
        self._first = -1
        self._pending = np.zeros(self.n)
        self._pending_taps: list[int] = []
        self.segments: list[tuple[int, int]] = []
        self.tap_lo = _Blocks(self.m * self.n, np.float32)
        self.tap_hi = _Blocks(2 + self.n, np.float64)
        self.taps = 0

    @classmethod
    def for_filter(cls, f, tap_rows: int = 9, precision: str = "float32") -> "StepRecorder":
        """A recorder for ``InsFilter`` f (its state layout)."""
        return cls(f.layout.n, transition_support(f.layout), tap_rows, precision)

    # ------------------------------------------------------------------ forward: the filter's calls
    def propagate(self, f, Phi: np.ndarray, dt_s: float) -> None:
        """``InsFilter._flush_covariance``, before P is propagated over ``dt_s`` to ``f.t_stamp_s``.
        While the heading is open the filter decouples the yaw after each propagation (P rewritten):
        no node is recorded then."""
        if not f.heading_known:
            self.close(f.P)
            return
        self.step(f.t_stamp_s - dt_s, f.t_stamp_s, f.P, Phi, f.q_c * dt_s)

    def propagating(self, f, Phi: np.ndarray, q_c: np.ndarray, dt_s: float) -> None:
        self.propagate(f, Phi, dt_s)

    def corrected(self, f, H: np.ndarray, d: np.ndarray, R: np.ndarray, dx: np.ndarray, nis: float,
                  S: np.ndarray) -> None:
        self.correct(dx)

    def states_reset(self, f, P_before: np.ndarray, index: np.ndarray) -> None:
        self.reset(f, P_before, index)

    def boundary(self, f) -> None:
        """Before a reset rewrites ``f.P``: the segment ends with the covariance it had."""
        self.close(f.P)

    def finish(self, f) -> None:
        """At the end of the recording (or before the filter is dropped)."""
        self.close(f.P)

    # ------------------------------------------------------------------ forward: generic steps
    def _new_node(self, t_s: float, dx: np.ndarray | None) -> None:
        i = self.nodes
        hi = self.hi.row(i)
        hi[0] = t_s
        if dx is not None:
            hi[self._hi[1]] = dx
        self.nodes += 1
        self._cur, self._cur_hi = i, hi

    def _store_P(self, i: int, P: np.ndarray, lo: np.ndarray | None = None, hi: np.ndarray | None = None) -> None:
        lo = self.lo.row(i) if lo is None else lo
        hi = self.hi.row(i) if hi is None else hi
        self.codec.encode(P, hi[self._hi[0]], lo[self._lo[0]])

    def step(self, t_from_s: float, t_to_s: float, P_plus: np.ndarray, Phi: np.ndarray, qdt: np.ndarray) -> None:
        """A propagation from the current node (time ``t_from_s``, covariance after its updates
        ``P_plus``) to a new node at ``t_to_s`` with transition Phi and process noise ``qdt``
        (diagonal of Q = q_c dt, applied as ``ekf.propagate_with_transition`` does)."""
        if self._cur < 0:
            self._new_node(t_from_s, self._pending)
            self._first = self._cur
            self._pending = np.zeros(self.n)
            for k in self._pending_taps:
                self.tap_hi.row(k)[1] = self._cur
            self._pending_taps = []
        i = self._cur
        lo = self.lo.row(i)
        self._store_P(i, P_plus, lo, self._cur_hi)
        block = Phi[self._block]
        rest = Phi.copy()
        rest[self._block] = self._eye_block
        if not np.array_equal(rest, self._eye):
            self.phi_full[i] = Phi.copy()
        lo[self._lo[1]] = (block - self._eye_block).ravel()
        lo[self._lo[2]] = qdt
        self._new_node(t_to_s, None)

    def correct(self, dx: np.ndarray) -> None:
        """A correction fed back into the nominal state at the current node."""
        if self._cur >= 0:
            self._cur_hi[self._hi[1]] += dx
        else:
            self._pending += dx

    def close(self, P_now: np.ndarray) -> None:
        """End the current segment: ``P_now`` is the last node's covariance after its updates."""
        if self._cur >= 0:
            self._store_P(self._cur, P_now, hi=self._cur_hi)
            if self._cur > self._first:
                self.segments.append((self._first, self._cur))
        self._cur, self._cur_hi = -1, None
        self._pending = np.zeros(self.n)
        self._pending_taps = []

    def reset(self, f, P_before: np.ndarray, decoupled: np.ndarray) -> None:
        """After ``f`` rewrote its P from ``P_before``, giving the states ``decoupled`` fresh
        estimates of their own (``InsFilter._update_static_calibration``: the gyro biases reset to
        a stop's estimate): a transition when it has that form (``reset_transition``), else a
        boundary."""
        self.transition(f.t_stamp_s, P_before, f.P, decoupled)

    def transition(self, t_s: float, P_before: np.ndarray, P_after: np.ndarray, decoupled: np.ndarray) -> None:
        """A rewrite of the covariance at the current node (the nominal state unchanged except in
        the states ``decoupled``): recorded as a node at the same time with the transition (T, Q)
        of ``reset_transition`` when P_after = T P_before T^T + Q, else the segment ends with
        P_before."""
        if self._cur < 0:
            return
        TQ = reset_transition(P_before, P_after, decoupled)
        if TQ is None:
            self.close(P_before)
            return
        i = self._cur
        self._store_P(i, P_before, hi=self._cur_hi)
        self.resets[i] = TQ
        self._new_node(t_s, None)

    def tap(self, t_s: float, J: np.ndarray) -> int:
        """An output to smooth at stamp time ``t_s`` (the filter's ``t_stamp_s``) with the rows J
        (m x n) of what is reported; returns its index in ``SmoothedTaps``."""
        k = self.taps
        hi = self.tap_hi.row(k)
        hi[0], hi[1] = t_s, self._cur
        self.tap_lo.row(k)[:] = np.ravel(J)
        if self._cur >= 0:
            hi[2:] = self._cur_hi[self._hi[1]]
        else:
            # before the segment's first node exists (it is opened by the next propagation, at the
            # time of this state): attached to it then
            hi[2:] = self._pending
            self._pending_taps.append(k)
        self.taps += 1
        return k

    def segment_times(self) -> list[tuple[float, float]]:
        """(first, last) node stamp times [s] of every smoothed segment."""
        return [(float(self.hi.row(a)[0]), float(self.hi.row(b)[0])) for a, b in self.segments]

    @property
    def stored_bytes(self) -> int:
        """Bytes held by the node and tap storage."""
        return (self.lo.nbytes + self.hi.nbytes + self.tap_lo.nbytes + self.tap_hi.nbytes
                + sum(v.nbytes for v in self.phi_full.values()))

    # ------------------------------------------------------------------ backward pass
    def _node(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(P+, Phi, q_c dt) of node i, decoded in float64."""
        lo, hi = self.lo.row(i).astype(np.float64), self.hi.row(i)
        P = self.codec.decode(hi[self._hi[0]], lo[self._lo[0]])
        if i in self.phi_full:
            Phi = self.phi_full[i]
        else:
            Phi = np.eye(self.n)
            Phi[self._block] += lo[self._lo[1]].reshape(self._block_shape)
        return P, Phi, lo[self._lo[2]]

    def smooth(self) -> SmoothedTaps:
        """The backward pass over every segment (module docstring); the taps' smoothed values."""
        n, m, K = self.n, self.m, self.taps
        f4 = self.codec.dtype
        out = SmoothedTaps(np.zeros(K, bool), np.zeros((K, n), f4), np.zeros((K, n), f4), np.zeros((K, m)),
                           np.zeros((K, m, m), f4))
        tap_node = np.array([self.tap_hi.row(k)[1] for k in range(K)]).astype(np.int64)
        on = np.flatnonzero(tap_node >= 0)
        on_nodes = tap_node[on]
        bounds = np.searchsorted(on_nodes, np.arange(self.nodes + 1), "left")
        for first, last in self.segments:
            xs = np.zeros(n)
            Ps = self._node(last)[0]
            for i in range(last - 1, first - 1, -1):
                if i in self.resets:
                    Pp = self._node(i)[0]
                    Phi, Q = self.resets[i]
                    Pm = Phi @ Pp @ Phi.T + Q
                else:
                    Pp, Phi, qdt = self._node(i)
                    Pm = propagate_with_transition(Pp, Phi, qdt, 1.0)
                xm = xs + self.hi.row(i + 1)[self._hi[1]]
                G = smoother_gain(Pp, Phi, Pm)
                xs_i = G @ xm
                Ps_i = Pp + G @ (Ps - Pm) @ G.T
                Ps_i += Ps_i.T
                Ps_i *= 0.5
                a, b = bounds[i], bounds[i + 1]
                if b > a:
                    self._fill_taps(out, on[a:b], i, xs_i, Ps_i, xm, Ps)
                xs, Ps = xs_i, Ps_i
        return out

    def _fill_taps(self, out: SmoothedTaps, taps: np.ndarray, i: int, xs_i: np.ndarray, Ps_i: np.ndarray,
                   xm_next: np.ndarray, Ps_next: np.ndarray) -> None:
        """Taps between node i (after its updates, smoothed ``xs_i``, ``Ps_i``) and node i+1 (before
        its updates, ``xm_next``, ``Ps_next``): linear interpolation in time (module docstring)."""
        hi_i = self.hi.row(i)
        t0, t1 = hi_i[0], self.hi.row(i + 1)[0]
        n, m = self.n, self.m
        span = t1 - t0
        dx_i = hi_i[self._hi[1]]
        for k in taps:
            hi = self.tap_hi.row(k)
            w = min(1.0, max(0.0, (hi[0] - t0) / span)) if span > 0 else 0.0
            e = (1.0 - w) * (xs_i + dx_i - hi[2:]) + w * xm_next
            P = (1.0 - w) * Ps_i + w * Ps_next
            J = self.tap_lo.row(k).astype(np.float64).reshape(m, n)
            out.smoothed[k] = True
            out.dx[k] = e
            out.sd[k] = np.sqrt(np.maximum(P.diagonal(), 0.0))
            out.y[k] = J @ e
            out.cov[k] = J @ P @ J.T


# ---------------------------------------------------------------------------------------- tap rows
def reported_rows(f) -> np.ndarray:
    """J (9 x n) of what ``InsFilter.nav_state`` reports -- the IMU point's position and velocity at
    the time label, the vehicle attitude -- at the filter's current state (``reported``)."""
    w_nb_b, a_n = f.kinematics_now()
    return reported_jacobian(f.layout, f.C_nb, f.fx.misalignment_rad, f.nav[3:6], a_n, w_nb_b)


def antenna_rows(f, t_s: float) -> np.ndarray:
    """H (3 x n): the error of the antenna position predicted from the filter's state to GPS time
    ``t_s`` (``replay_metrics.predicted_antenna``: ``r + C l + v (t_s - t_label)``): with errors as
    estimate minus truth ``dr + [(C l) x] phi + C dl + gap dv - v d(dt)``, the GNSS position model's
    rows (``updates``) -- the label's error d(dt) moves the state's true time."""
    H = np.zeros((3, f.layout.n))
    Cl = f.C_nb @ f.fx.lever_arm_m
    H[:, POS:POS + 3] = np.eye(3)
    H[:, VEL:VEL + 3] = (t_s - f.t_s) * np.eye(3)
    H[:, ATT:ATT + 3] = skew(Cl)
    i = f.layout.at("lever_arm")
    if i >= 0:
        H[:, i:i + 3] = f.C_nb
    i = f.layout.at("imu_time_offset")
    if i >= 0:
        H[:, i] = -f.nav[3:6]
    return H


def corrected_reported(lla: np.ndarray, v_ned_mps: np.ndarray, rpy_rad: np.ndarray,
                       y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lla, v, rpy) of a reported state corrected by its smoothed error ``y = J dx`` (the rows of
    ``reported_rows``: position NED, velocity NED, vehicle attitude error NED), as the filter
    corrects its own state (``InsFilter._apply``): position by curvilinear increments, velocity
    minus its error, attitude ``C <- exp([phi x]) C`` (``C_est = (I - [phi x]) C``)."""
    C = dcm_from_euler(*np.asarray(rpy_rad, float))
    return (ned_correction_lla(lla, y[0:3]), np.asarray(v_ned_mps, float) - y[3:6],
            euler_from_dcm(exp_so3(y[6:9]) @ C))


def smoothed_nav_state(nav: NavState, y: np.ndarray, cov: np.ndarray, fix: FixStatus,
                       time_offset_error_s: float = 0.0, timing_rows: np.ndarray | None = None) -> NavState:
    """``nav`` (``InsFilter.nav_state``) with position, velocity and attitude corrected by the
    smoothed error ``y`` = J dx (``corrected_reported``), their sds and the position's correlations
    from the smoothed covariance ``cov`` (= J P^s J^T, 9 x 9) and the given fix; body rate and
    acceleration and the filter's flags are the forward state's.

    With the smoothed error of the IMU time offset ``time_offset_error_s`` (estimate minus truth)
    and J's column of that state ``timing_rows`` (``reported``: -v, -a, C w), the state is moved
    to the smoothed time label ``t_s - time_offset_error_s`` instead: the time-offset part of y
    (what moves the quantities along the trajectory to the forward label) is left out of the
    correction. The covariance is the same J P^s J^T: the smoothed label keeps the smoothed
    offset's own uncertainty."""
    t_s = nav.t_s
    if timing_rows is not None and time_offset_error_s:
        y = np.asarray(y, float) - time_offset_error_s * np.asarray(timing_rows, float)
        t_s = nav.t_s - float(time_offset_error_s)
    lla, v, rpy = corrected_reported(nav.lla, nav.v_ned_mps, nav.rpy_rad, y)
    cov = np.asarray(cov, float)
    sd = np.sqrt(np.maximum(np.diagonal(cov), 0.0))
    return replace(nav, t_s=t_s, lla=lla, v_ned_mps=v, rpy_rad=rpy, pos_sd_m=sd[0:3], vel_sd_mps=sd[3:6],
                   att_sd_rad=sd[6:9], pos_corr=correlations(cov[0:3, 0:3]), fix=FixStatus(int(fix)))


def ned_correction_lla(lla: np.ndarray, d_ned_m: np.ndarray) -> np.ndarray:
    """lla (rad, m) moved by minus an NED error ``d_ned_m`` (curvilinear increments, as
    ``InsFilter._apply`` corrects its position)."""
    from v2xpos import geo
    lat, h = float(lla[0]), float(lla[2])
    r_m, r_n = geo.radii_m(lat)
    return np.array([lla[0] - d_ned_m[0] / (r_m + h), lla[1] - d_ned_m[1] / ((r_n + h) * math.cos(lat)),
                     lla[2] + d_ned_m[2]])
