"""What an ``InsFilter`` tells the objects that follow its steps without being part of them.

The filter's own step is the error-state Kalman filter: ``predict`` (the covariance brought to the
filter's time) and ``correct`` (one measurement). Two machineries need to see every such step and
must not change it:

* the fault-tolerant twin of the integrity model (``integrity.FaultTolerantSolution``): the same
  filter on the same measurements started with the declared set-up widened, propagated with the
  filter's transition and updated with the measurements the filter accepted;
* the smoother's recorder (``smoother.StepRecorder``): the transitions, corrections and resets a
  backward (Rauch-Tung-Striebel) pass needs.

Both implement :class:`FilterObserver`; the filter calls every observer at the same four points
(robot_localization's filter base separates the Kalman step from what listens to it the same way).
An observer may read the filter it is given; it must not change it -- an action on the filter (the
integrity model's exclusion of the declared set-up) is a filter step of its own.
"""
from __future__ import annotations

import numpy as np


class FilterObserver:
    """No-op base: override the points an observer needs."""

    def propagating(self, f, Phi: np.ndarray, q_c: np.ndarray, dt_s: float) -> None:
        """Before ``f.P`` is propagated over ``dt_s`` (to ``f.t_stamp_s``) with the transition
        ``Phi`` and the process-noise density ``q_c``: P <- Phi P Phi^T + Q(q_c, dt_s)."""

    def corrected(self, f, H: np.ndarray, d: np.ndarray, R: np.ndarray, dx: np.ndarray, nis: float,
                  S: np.ndarray) -> None:
        """After an accepted measurement (model ``H``, innovation ``d``, noise ``R``; the filter's
        NIS and innovation covariance ``S``) moved the state by ``dx`` and ``f.P`` was updated."""

    def states_reset(self, f, P_before: np.ndarray, index: np.ndarray) -> None:
        """After ``f`` replaced the states ``index`` by fresh estimates decoupled from the rest
        (``f.P`` rewritten from ``P_before``), e.g. the gyro biases a refuted stop check resets."""

    def boundary(self, f) -> None:
        """Before a reset that rewrites ``f.P`` and moves the state (a start, a position or heading
        reset, the exclusion of the declared set-up): nothing carries across it."""
