"""Residual capture: every measurement update's innovation with the motion state at the same time.

``ResidualRecorder.record(update_result, nav_state)`` is the hook the replay calls after each
update (GNSS position/velocity, NHC, ZUPT, odometer); ``finish()`` returns a ``ResidualLog`` of
column arrays per measurement kind. Innovations are z - h(x) (measurement minus prediction) in
the measurement's own axes (NED for GNSS, vehicle frame for NHC/odometer); ``sd`` is
sqrt(diag(S)). Motion signals (body = the filter's vehicle frame, x fwd, y right, z down):
v_ned_mps, C_nb (body -> NED), rate_body_rps, acc_body_mps2 (kinematic), f_body_mps2 (specific
force f = a - C_bn g_n), speed_mps.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from v2xpos import geo
from v2xpos.rotation import dcm_from_euler


@dataclass
class ResidualSet:
    """Innovations of one measurement kind, one row per update (also gated-out ones)."""
    kind: str
    t_s: np.ndarray
    innovation: np.ndarray
    sd: np.ndarray
    nis: np.ndarray
    accepted: np.ndarray
    v_ned_mps: np.ndarray
    C_nb: np.ndarray
    rate_body_rps: np.ndarray
    acc_body_mps2: np.ndarray
    f_body_mps2: np.ndarray

    def __len__(self) -> int:
        return len(self.t_s)

    @property
    def speed_mps(self) -> np.ndarray:
        return np.linalg.norm(self.v_ned_mps[:, :2], axis=1)

    @property
    def rpy_rad(self) -> np.ndarray:
        from v2xpos.rotation import euler_from_dcm_batch
        return euler_from_dcm_batch(self.C_nb)

    def in_body(self) -> np.ndarray:
        """NED innovations resolved in the body frame, C_bn nu (only for 3-component NED kinds)."""
        return np.einsum("nji,nj->ni", self.C_nb, self.innovation)

    def select(self, mask: np.ndarray) -> "ResidualSet":
        return ResidualSet(self.kind, *(getattr(self, f)[mask] for f in _ARRAY_FIELDS))


_ARRAY_FIELDS = ("t_s", "innovation", "sd", "nis", "accepted", "v_ned_mps", "C_nb", "rate_body_rps",
                 "acc_body_mps2", "f_body_mps2")


@dataclass
class ResidualLog:
    """All captured residuals of one replay, by kind ('gnss_pos', 'gnss_vel', 'nhc', ...)."""
    sets: dict[str, ResidualSet] = field(default_factory=dict)

    def __getitem__(self, kind: str) -> ResidualSet:
        return self.sets[kind]

    def __contains__(self, kind: str) -> bool:
        return kind in self.sets

    def kinds(self) -> list[str]:
        return sorted(self.sets)

    def nis_mean(self, kinds: tuple = ("gnss_pos", "gnss_vel")) -> float:
        vals = [self.sets[k].nis[self.sets[k].accepted] for k in kinds if k in self.sets]
        vals = np.concatenate(vals) if vals else np.zeros(0)
        return float(np.mean(vals)) if len(vals) else float("nan")


class ResidualRecorder:
    """Collects update results and the navigation state at each update."""

    def __init__(self, kinds: tuple | None = None, decimate: dict[str, int] | None = None):
        self.kinds = kinds
        self.decimate = decimate or {}
        self._rows: dict[str, list] = {}
        self._count: dict[str, int] = {}

    def record(self, result, nav) -> None:
        """result: an update result with kind, t_s, accepted, nis, innovation, innovation_sd;
        nav: a NavState (rpy_rad, v_ned_mps, rate_body_rps, acc_body_mps2, lla)."""
        kind = str(getattr(result, "kind", ""))
        if self.kinds is not None and kind not in self.kinds:
            return
        c = self._count.get(kind, 0)
        self._count[kind] = c + 1
        if c % max(1, self.decimate.get(kind, 1)):
            return
        self._rows.setdefault(kind, []).append((result, nav))

    __call__ = record

    def finish(self) -> ResidualLog:
        log = ResidualLog()
        for kind, rows in self._rows.items():
            m = max(len(np.atleast_1d(r.innovation)) for r, _ in rows)
            n = len(rows)
            inn = np.full((n, m), np.nan)
            sd = np.full((n, m), np.nan)
            C = np.empty((n, 3, 3))
            arr = {k: np.empty((n, 3)) for k in ("v", "w", "a", "f")}
            t = np.empty(n)
            nis = np.empty(n)
            acc = np.empty(n, bool)
            for i, (r, nav) in enumerate(rows):
                x = np.atleast_1d(np.asarray(r.innovation, float))
                s = np.atleast_1d(np.asarray(getattr(r, "innovation_sd", np.full(len(x), np.nan)), float))
                inn[i, :len(x)] = x
                sd[i, :len(s)] = s
                t[i] = float(r.t_s)
                nis[i] = float(r.nis)
                acc[i] = bool(r.accepted)
                C[i] = dcm_from_euler(*nav.rpy_rad)
                arr["v"][i] = nav.v_ned_mps
                arr["w"][i] = nav.rate_body_rps
                arr["a"][i] = nav.acc_body_mps2
                g = geo.normal_gravity_mps2(nav.lla[0], nav.lla[2])
                arr["f"][i] = np.asarray(nav.acc_body_mps2) - C[i][2, :] * g
            log.sets[kind] = ResidualSet(kind, t, inn, sd, nis, acc, arr["v"], C, arr["w"], arr["a"], arr["f"])
        return log
