"""Second parameter: fuse every unit separately with position fixes, compare the fused
solutions of unit under test and reference.

Each unit drives its own ``v2xpos.ins.InsFilter`` (platform "generic") with the same position
fixes (GNSS, or the recording's reference trajectory used as a fix source). All filters share one
body frame, the reference unit's axes: the unit under test enters with ``imu_to_body = C_ref_ut``
from the alignment, so its fused attitude is directly comparable. At every fix epoch, just before
the update, the fused states are sampled and

    d_att = |log(C_nb,ref^T C_nb,ut)|  [deg],    d_pos = |r_ut - r_ref|  [m]

are collected; P50 / P90 / P99 of both series (after ``settle_s``) are the second parameter.

Initial attitude (the mounting of the units on the vehicle is not declared): in-motion alignment
by Wahba's problem over the first ``align_s`` seconds (optimisation-based alignment, Wu & Pan
2013, IEEE TAES 49(2)): with C_b0_bk from integrating the gyro, over intervals i
    alpha_i = int C_b0_b f_b dt  (body frame at t0),   beta_i = dv_n,i - g_n dt_i  (NED, from fixes)
and beta_i = C_n_b0 alpha_i, solved with ``unit_rotation.kabsch_rotation``.
"""
from __future__ import annotations

import numpy as np

from v2xpos import geo
from v2xpos.rotation import dcm_from_euler, euler_from_dcm, exp_so3, log_so3
from v2xpos.types import FixStatus, ImuData

from .unit_rotation import kabsch_rotation

NOMINAL_ORIGIN_LLA = np.array([np.radians(45.0), 0.0, 0.0])
"""Origin given to positions known only in a local NED frame (the result does not depend on it
beyond the small change of gravity and Earth rate with latitude)."""


def _velocity_from_positions(t_s: np.ndarray, r_ned_m: np.ndarray) -> np.ndarray:
    """Central-difference velocity [m/s] of a position series."""
    return np.stack([np.gradient(r_ned_m[:, k], t_s) for k in range(3)], axis=1)


def align_in_motion(imu: ImuData, C_body_imu: np.ndarray, t_fix_s: np.ndarray, r_ned_m: np.ndarray,
                    t0_s: float, align_s: float = 5.0, interval_s: float = 0.5,
                    gravity_mps2: float = geo.G0_MPS2) -> np.ndarray:
    """C_n_b at t0_s (body = C_body_imu @ imu axes) from gyro, accel and position fixes (module doc)."""
    sel = (imu.t_s >= t0_s) & (imu.t_s <= t0_s + align_s)
    t = imu.t_s[sel]
    w = imu.gyro_rps[sel] @ C_body_imu.T
    f = imu.acc_mps2[sel] @ C_body_imu.T
    if len(t) < 10:
        raise ValueError("align_in_motion: fewer than 10 IMU samples in the alignment window")
    C = np.eye(3)
    fb0 = np.empty_like(f)
    fb0[0] = f[0]
    for k in range(1, len(t)):
        C = C @ exp_so3(0.5 * (w[k - 1] + w[k]) * (t[k] - t[k - 1]))
        fb0[k] = C @ f[k]
    v = _velocity_from_positions(t_fix_s, r_ned_m)
    edges = np.arange(t0_s, t0_s + align_s + 1e-9, interval_s)
    cum = np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (fb0[1:] + fb0[:-1]) * np.diff(t)[:, None], axis=0)])
    alpha, beta = [], []
    g_n = np.array([0.0, 0.0, gravity_mps2])
    for a, b in zip(edges[:-1], edges[1:]):
        if b > t[-1] or a < t[0]:
            continue
        ia = np.array([np.interp(a, t, cum[:, k]) for k in range(3)])
        ib = np.array([np.interp(b, t, cum[:, k]) for k in range(3)])
        va = np.array([np.interp(a, t_fix_s, v[:, k]) for k in range(3)])
        vb = np.array([np.interp(b, t_fix_s, v[:, k]) for k in range(3)])
        alpha.append(ib - ia)
        beta.append(vb - va - g_n * (b - a))
    if len(alpha) < 3:
        raise ValueError("align_in_motion: not enough intervals with both IMU data and fixes")
    return kabsch_rotation(np.array(beta), np.array(alpha), center=False)


def fuse_unit(imu: ImuData, C_body_imu: np.ndarray, t_fix_s: np.ndarray, r_ned_m: np.ndarray,
              C_nb0: np.ndarray, fix_sd_m: float = 0.05, origin_lla: np.ndarray = NOMINAL_ORIGIN_LLA,
              lever_arm_m: np.ndarray | None = None, gyro_noise_rps_rthz: float | None = None,
              accel_noise_mps2_rthz: float | None = None) -> dict:
    """Run one unit through ``InsFilter`` with position fixes; returns the fused states sampled just
    before each fix: {'t_s', 'r_ned_m' (N,3), 'C_nb' (N,3,3)} (body = C_body_imu @ imu axes).
    gyro/accel noise densities: the filter's white-noise model (None: the InsConfig default)."""
    from v2xpos.ins import InsConfig, InsFilter
    from v2xpos.ins.driver import InsDriver

    cfg = InsConfig(setup={"platform": "generic", "imu_to_body": C_body_imu,
                           "lever_arm_m": np.zeros(3) if lever_arm_m is None else lever_arm_m, "lever_arm_sd_m": 0.05},
                    gnss={"use_gnss_velocity": False}, stops={"apply_static_calibration": False})
    if gyro_noise_rps_rthz is not None:
        cfg.imu.gyro_noise_rps_rthz = gyro_noise_rps_rthz
    if accel_noise_mps2_rthz is not None:
        cfg.imu.accel_noise_mps2_rthz = accel_noise_mps2_rthz
    filt = InsFilter(cfg)
    v = _velocity_from_positions(t_fix_s, r_ned_m)
    t0 = float(t_fix_s[0])
    lla_fix = geo.ned_to_lla(r_ned_m, origin_lla)
    sampler = _before_each_fix(origin_lla)
    drv = InsDriver(filt, complete=True, hooks=[sampler])
    drv.push_imu_block(imu.t_s, imu.acc_mps2, imu.gyro_rps)
    drv.initialize(t0, lla_fix[0], v[0], euler_from_dcm(C_nb0), pos_sd_m=fix_sd_m,
                   att_sd_rad=np.radians([2.0, 2.0, 5.0]))
    for k in range(1, len(t_fix_s)):
        drv.push_gnss(float(t_fix_s[k]), lla_fix[k], np.full(3, fix_sd_m), FixStatus.FIXED)
    drv.run()
    return {"t_s": np.array(sampler.t_s), "r_ned_m": np.array(sampler.r_ned_m), "C_nb": np.array(sampler.C_nb)}


def _before_each_fix(origin_lla: np.ndarray):
    """A driver hook keeping the fused state just before each fix's update: its time, position in
    the local NED frame about ``origin_lla`` and C_nb."""
    from v2xpos.ins.driver import DriverHook

    class BeforeEachFix(DriverHook):
        def __init__(self) -> None:
            self.t_s: list = []
            self.r_ned_m: list = []
            self.C_nb: list = []

        def on_gnss_epoch(self, f, t_s: float, k: int, used: bool) -> None:
            ns = f.nav_state()
            self.t_s.append(float(t_s))
            self.r_ned_m.append(geo.lla_to_ned(ns.lla[None, :], origin_lla)[0])
            self.C_nb.append(dcm_from_euler(*ns.rpy_rad))

    return BeforeEachFix()


def percentiles(x: np.ndarray) -> dict:
    """{'p50','p90','p99'} of a series (None when empty)."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {"p50": None, "p90": None, "p99": None}
    p = np.percentile(x, [50, 90, 99])
    return {"p50": float(p[0]), "p90": float(p[1]), "p99": float(p[2])}


def fused_differences(units: dict[str, ImuData], reference: str, C_ref_unit: dict,
                      t_fix_s: np.ndarray, r_ned_m: np.ndarray, fix_sd_m: float = 0.05,
                      align_s: float = 5.0, settle_s: float = 2.0,
                      time_offset_s: dict | None = None, noise_density: dict | None = None) -> dict:
    """Second parameter for every unit against the reference (module doc).

    C_ref_unit: unit id -> rotation unit axes -> reference axes (identity for the reference);
    time_offset_s: unit id -> clock offset against the reference (``ut(t + off) ~ ref(t)``), removed
    from the unit's stamps before fusion; noise_density: unit id -> (gyro rad/s/rtHz, accel
    m/s^2/rtHz) for the filters (default: the InsConfig defaults). Returns unit id -> {'att_deg': {...}, 'pos_m': {...},
    'n_epochs'}; the reference gets zeros by construction and is omitted.
    """
    t_fix_s = np.asarray(t_fix_s, float)
    r_ned_m = np.asarray(r_ned_m, float)
    t0 = max(float(t_fix_s[0]), max(float(u.t_s[0]) for u in units.values()))
    keep = t_fix_s >= t0
    t_fix_s, r_ned_m = t_fix_s[keep], r_ned_m[keep]
    ref_imu = units[reference]
    C_nb0 = align_in_motion(ref_imu, np.eye(3), t_fix_s, r_ned_m, float(t_fix_s[0]), align_s)
    sol = {}
    for uid, imu in units.items():
        off = (time_offset_s or {}).get(uid, 0.0)
        imu_c = ImuData(t_s=imu.t_s - off, acc_mps2=imu.acc_mps2, gyro_rps=imu.gyro_rps)
        ng, na = (noise_density or {}).get(uid, (None, None))
        sol[uid] = fuse_unit(imu_c, np.asarray(C_ref_unit[uid]), t_fix_s, r_ned_m, C_nb0, fix_sd_m,
                             gyro_noise_rps_rthz=ng, accel_noise_mps2_rthz=na)
    ref = sol[reference]
    out = {}
    for uid, s in sol.items():
        if uid == reference:
            continue
        n = min(len(s["t_s"]), len(ref["t_s"]))
        sel = s["t_s"][:n] >= s["t_s"][0] + settle_s
        d_pos = np.linalg.norm(s["r_ned_m"][:n] - ref["r_ned_m"][:n], axis=1)[sel]
        d_att = np.array([np.degrees(np.linalg.norm(log_so3(ref["C_nb"][k].T @ s["C_nb"][k])))
                          for k in range(n)])[sel]
        out[uid] = {"att_deg": percentiles(d_att), "pos_m": percentiles(d_pos), "n_epochs": int(sel.sum()),
                    "fix_source": "reference trajectory"}
    return out

