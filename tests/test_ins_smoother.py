"""The smoother (``v2xpos.ins.smoother``): the Rauch-Tung-Striebel pass over a closed-loop filter
against the batch solution of a small linear system (known answer), the closed-loop feedback terms,
segment boundaries, the storage, and the recorder on ``InsFilter`` (it must not change the filter)."""
from __future__ import annotations

import numpy as np
import pytest

from v2xpos.ins.ekf import propagate_with_transition
from v2xpos.ins.smoother import CovarianceCodec, StepRecorder, smoother_gain

N_STATES, N_MEAS, N_STEPS = 5, 2, 30


def linear_system(seed: int = 1):
    """x_{k+1} = Phi x_k + w_k, Q as ``ekf.propagate_with_transition`` applies it (half before, half
    after the transition); z_k = H x_k + v_k at two of every three steps."""
    rng = np.random.default_rng(seed)
    n, m = N_STATES, N_MEAS
    sys = {"Phi": np.eye(n) + 0.1 * rng.standard_normal((n, n)), "q": 0.05 * np.abs(rng.standard_normal(n)),
           "H": rng.standard_normal((m, n)), "R": np.diag([0.3, 0.2]), "m0": rng.standard_normal(n),
           "P0": np.diag(np.abs(rng.standard_normal(n)) + 0.5),
           "measured": [k % 3 != 1 for k in range(N_STEPS + 1)]}
    Qh = np.diag(0.5 * sys["q"])
    sys["Q"] = sys["Phi"] @ Qh @ sys["Phi"].T + Qh
    x = rng.multivariate_normal(sys["m0"], sys["P0"])
    z = []
    for k in range(N_STEPS + 1):
        if k:
            x = sys["Phi"] @ x + rng.multivariate_normal(np.zeros(n), sys["Q"])
        z.append(sys["H"] @ x + rng.multivariate_normal(np.zeros(m), sys["R"]))
    sys["z"] = z
    return sys


def batch_solution(sys, k_end: int = N_STEPS, reset: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Posterior mean and covariance of all states 0..k_end (and, with ``reset = (k, T, c, Q)``, of
    the state after a reset x' = T x_k + c + w, cov(w) = Q, inserted after step k) given every
    measurement up to k_end: the joint prior of the stacked states by the linear model, conditioned
    on all measurements at once (no recursion)."""
    n = N_STATES
    steps = []                                   # (transition, offset, noise, measured step or None)
    for k in range(1, k_end + 1):
        steps.append((sys["Phi"], np.zeros(n), sys["Q"], k))
        if reset is not None and reset[0] == k:
            steps.append((reset[1], reset[2], reset[3], None))
    if reset is not None and reset[0] == 0:
        steps.insert(0, (reset[1], reset[2], reset[3], None))
    K = len(steps) + 1
    mu = [sys["m0"]]
    S = np.zeros((K * n, K * n))
    S[:n, :n] = sys["P0"]
    rows = [0 if sys["measured"][0] else None]
    for j, (A, c, Q, k) in enumerate(steps, start=1):
        mu.append(A @ mu[-1] + c)
        prev, cur = slice((j - 1) * n, j * n), slice(j * n, (j + 1) * n)
        S[cur, :j * n] = A @ S[prev, :j * n]
        S[:j * n, cur] = S[cur, :j * n].T
        S[cur, cur] = A @ S[prev, prev] @ A.T + Q
        rows.append(k if k is not None and sys["measured"][k] else None)
    M, z = [], []
    for j, k in enumerate(rows):
        if k is not None:
            Mj = np.zeros((N_MEAS, K * n))
            Mj[:, j * n:(j + 1) * n] = sys["H"]
            M.append(Mj)
            z.append(sys["z"][k])
    M, z, m = np.vstack(M), np.concatenate(z), np.concatenate(mu)
    R = np.kron(np.eye(len(z) // N_MEAS), sys["R"])
    gain = S @ M.T @ np.linalg.inv(M @ S @ M.T + R)
    mean, C = m + gain @ (z - M @ m), S - gain @ M @ S
    return mean.reshape(K, n), np.array([C[j * n:(j + 1) * n, j * n:(j + 1) * n] for j in range(K)])


def closed_loop_run(sys, rec: StepRecorder | None, feed_back: bool = True, split_updates: bool = False,
                    boundary_at: int | None = None, reset: tuple | None = None):
    """A closed-loop error-state filter on the linear system: the nominal x carries the estimate, an
    update estimates the error dx = K (H x - z) (estimate minus truth) and feeds it back, x <- x - dx.
    Taps (J = I) after every step's updates (and, with ``split_updates``, between a step's two scalar
    updates). ``boundary_at``: a reset there (the covariance back to the prior around the estimate).
    ``reset = (k, T, Q, x_new)``: after step k's updates the states T decouples get the estimate
    ``x_new`` and P <- T P T^T + Q (a reset of those states to a fresh estimate, the others kept).
    Returns (tap index, step, nominal) per tap, the last estimate and covariance, and the estimate
    at the reset."""
    x, P = sys["m0"].copy(), sys["P0"].copy()
    Phi, H, R = sys["Phi"], sys["H"], sys["R"]
    taps, x_reset = [], None

    def update(rows: slice) -> None:
        nonlocal x, P
        h, r = H[rows], R[rows, rows]
        d = h @ x - sys["z"][k][rows]
        K = P @ h.T @ np.linalg.inv(h @ P @ h.T + r)
        dx = K @ d
        P = P - K @ h @ P
        P = 0.5 * (P + P.T)
        x = x - dx
        if rec is not None and feed_back:
            rec.correct(dx)

    for k in range(N_STEPS + 1):
        if k:
            if boundary_at == k:
                rec.close(P)
                P = sys["P0"].copy()
            rec.step(k - 1, k, P, Phi, sys["q"])
            P = propagate_with_transition(P, Phi, sys["q"], 1.0)
            x = Phi @ x
        if sys["measured"][k]:
            if split_updates:
                update(slice(0, 1))
                taps.append((rec.tap(k, np.eye(N_STATES)), k, x.copy()))
                update(slice(1, 2))
            else:
                update(slice(0, 2))
        if reset is not None and reset[0] == k:
            T_r, Q_r, x_new = reset[1:]
            P_after = T_r @ P @ T_r.T + Q_r
            rec.transition(k, P, P_after, np.flatnonzero(np.diag(T_r) == 0.0))
            x = T_r @ x + (np.eye(N_STATES) - T_r) @ x_new
            P, x_reset = P_after, x.copy()
        taps.append((rec.tap(k, np.eye(N_STATES)), k, x.copy()))
    rec.close(P)
    return taps, x, P, x_reset


@pytest.mark.parametrize("precision, tol", [("float64", 1e-9), ("float32", 1e-5)])
def test_rts_equals_the_batch_solution(precision, tol):
    """Every smoothed state and covariance equals the batch posterior of the whole record (the last
    tap lies after the last node: not smoothed, its forward values are the batch's there)."""
    sys = linear_system()
    rec = StepRecorder(N_STATES, None, tap_rows=N_STATES, precision=precision)
    taps, x_end, P_end, _ = closed_loop_run(sys, rec)
    mean, cov = batch_solution(sys)
    sm = rec.smooth()
    for k_tap, k, x_nom in taps:
        if k == N_STEPS:
            assert not sm.smoothed[k_tap]
            continue
        assert sm.smoothed[k_tap]
        scale = np.sqrt(np.diag(cov[k]))
        assert np.max(np.abs((x_nom - sm.dx[k_tap]) - mean[k]) / scale) < tol
        assert np.max(np.abs(sm.cov[k_tap] - cov[k]) / np.outer(scale, scale)) < tol
        assert np.allclose(sm.y[k_tap], sm.dx[k_tap], atol=1e-6)
        assert np.allclose(sm.sd[k_tap], scale, rtol=tol)
    assert np.allclose(x_end, mean[-1]) and np.allclose(P_end, cov[-1])


def test_closed_loop_corrections_are_needed_and_a_tap_between_updates_gets_the_rest():
    """The feedback terms: the same run without telling the recorder the corrections smooths to a
    different (wrong) answer; a tap taken between two updates of one step (its nominal has only the
    first correction) is smoothed to the same state as a tap after both."""
    sys = linear_system(seed=3)
    mean, _ = batch_solution(sys)
    rec = StepRecorder(N_STATES, None, tap_rows=N_STATES, precision="float64")
    taps, _, _, _ = closed_loop_run(sys, rec, split_updates=True)
    sm = rec.smooth()
    between = 0
    for k_tap, k, x_nom in taps:
        if k < N_STEPS:
            assert np.allclose(x_nom - sm.dx[k_tap], mean[k], atol=1e-8)
            between += 1
    assert between > N_STEPS          # the taps between two updates were checked too
    rec = StepRecorder(N_STATES, None, tap_rows=N_STATES, precision="float64")
    taps, _, _, _ = closed_loop_run(sys, rec, feed_back=False)
    sm = rec.smooth()
    worst = max(np.max(np.abs(x_nom - sm.dx[k_tap] - mean[k])) for k_tap, k, x_nom in taps if k < N_STEPS)
    assert worst > 0.05


def test_a_boundary_splits_the_record():
    """Before a reset the smoothed states are the batch solution of the data up to it (what comes
    after a reset that discards information does not reach back); after it, of the data from it."""
    sys = linear_system(seed=5)
    k_b = 12
    rec = StepRecorder(N_STATES, None, tap_rows=N_STATES, precision="float64")
    taps, _, _, _ = closed_loop_run(sys, rec, boundary_at=k_b)
    sm = rec.smooth()
    assert len(rec.segments) == 2
    mean_a, _ = batch_solution(sys, k_b - 1)
    for k_tap, k, x_nom in taps:
        if k < k_b - 1:
            assert np.allclose(x_nom - sm.dx[k_tap], mean_a[k], atol=1e-8)
        if k == k_b - 1:
            assert not sm.smoothed[k_tap]       # the last node of the first segment


def test_codec_round_trip_and_a_state_without_variance():
    rng = np.random.default_rng(7)
    A = rng.standard_normal((8, 8))
    P = A @ A.T * np.outer(np.logspace(-6, 1, 8), np.logspace(-6, 1, 8))
    P[3, :] = P[:, 3] = 0.0
    for precision, tol in (("float32", 1e-6), ("float64", 1e-15)):
        c = CovarianceCodec(8, precision)
        scale, packed = np.zeros(c.scale_width), np.zeros(c.width, c.dtype)
        c.encode(P, scale, packed)
        Q = c.decode(scale, packed.astype(float))
        d = np.sqrt(np.maximum(np.diag(P), 1e-300))
        assert np.max(np.abs(Q - P) / np.outer(d, d)) < tol
        assert np.linalg.eigvalsh(Q).min() > -1e-12 * np.abs(Q).max()
    Pm = propagate_with_transition(P, np.eye(8), np.zeros(8), 1.0)
    G = smoother_gain(P, np.eye(8), Pm)
    assert np.all(G[:, 3] == 0.0) and np.allclose(np.delete(np.delete(G, 3, 0), 3, 1), np.eye(7), atol=1e-6)


def test_a_decoupling_reset_is_a_transition_not_a_boundary():
    """A covariance rewrite that gives a block of states a fresh estimate and covariance of its own
    (decoupled from the rest, e.g. the gyro biases reset to a stop's estimate) and adds variance
    elsewhere is smoothed across as the transition x' = T x + (I - T) x_new + w, cov(w) = Q: the
    smoothed states on both sides equal the batch solution of that model over the whole record; the
    recorder found Q from the two covariances and the decoupled states."""
    sys = linear_system(seed=9)
    k_r = 14
    T = np.eye(N_STATES)
    T[2, 2] = T[3, 3] = 0.0
    g = np.array([1.0, -0.5, 0.0, 0.0, 0.3])
    Q = 0.3 * np.outer(g, g)
    Q[2:4, 2:4] = [[2.0, 0.5], [0.5, 1.0]]
    x_new = np.array([0.0, 0.0, 1.5, -0.7, 0.0])
    rec = StepRecorder(N_STATES, None, tap_rows=N_STATES, precision="float64")
    taps, _, _, x_reset = closed_loop_run(sys, rec, reset=(k_r, T, Q, x_new))
    assert len(rec.segments) == 1 and len(rec.resets) == 1
    T_found, Q_found = next(iter(rec.resets.values()))
    assert np.allclose(T_found, T) and np.allclose(Q_found, Q)
    from v2xpos.ins.smoother import reset_transition
    P_b = np.diag([1.0, 2.0, 3.0, 4.0, 5.0]) + 0.5
    assert reset_transition(P_b, P_b - 0.1 * np.eye(N_STATES), [2, 3]) is None   # other states lost variance
    mean, _ = batch_solution(sys, reset=(k_r, T, (np.eye(N_STATES) - T) @ x_reset, Q))
    sm = rec.smooth()
    for k_tap, k, x_nom in taps:
        if k == N_STEPS:
            continue
        j = k + (1 if k >= k_r else 0)          # the batch's index: the reset adds a state after step k_r
        assert np.allclose(x_nom - sm.dx[k_tap], mean[j], atol=1e-8), k
