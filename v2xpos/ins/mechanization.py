"""Strapdown INS mechanization in the local-level NED frame, jitted over whole batches of samples.

Frames: n = local-level NED at the current position; b = the filter's body frame (the IMU axes
turned by the *nominal* mounting, x forward, y right, z down); ``C_nb`` takes b -> n.

Per IMU interval [t_{k-1}, t_k] the sampled rates are turned into increments by the trapezoid rule,
``dtheta_k = (w_{k-1} + w_k) dt / 2`` and ``dv_k = (f_{k-1} + f_k) dt / 2``, and integrated with the
two-sample second-order algorithm of Shin (2001, "Accuracy improvement of low cost INS/GPS for land
applications", ch. 2) / Savage (1998, "Strapdown inertial navigation integration algorithm design",
JGCD 21(1-2)), as in KF-GINS:

    velocity:  dv_rot   = 1/2 dtheta_k x dv_k                                  (rotation)
               dv_scul  = 1/12 (dtheta_{k-1} x dv_k + dv_{k-1} x dtheta_k)    (sculling)
               zeta     = (w_ie^n + w_en^n)|_{k-1/2} dt
               dv_f^n   = (I - 1/2 [zeta x]) C_nb,{k-1} (dv_k + dv_rot + dv_scul)
               v_k      = v_{k-1} + dv_f^n + (g^n - (2 w_ie^n + w_en^n) x v)|_{k-1/2} dt
    position:  lat, lon, h from the mean velocity (Groves 2013 eq. 5.56, trapezoid)
    attitude:  phi_k    = dtheta_k + 1/12 dtheta_{k-1} x dtheta_k               (coning)
               C_nb,k   = exp(-[zeta x]) C_nb,{k-1} exp([phi_k x])             (Rodrigues)

Mid-interval Earth and transport rates use the previous position and the extrapolated velocity.
Gravity, radii of curvature and the SO(3) exponential are the compiled ones of ``v2xpos.kernels``.

The same loop accumulates the error-state dynamics matrix (see ``ekf.py``) as
``A += F(t_k) dt`` so that covariance propagation can run at a lower rate with
``Phi = I + A + A^2/2`` (docs/ins.md, "covariance propagation").
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from v2xpos.kernels import OMEGA_IE_RPS, cross_into, exp_so3_into, normal_gravity, radii

# nav vector layout: lat_rad, lon_rad, h_m, vN, vE, vD [m/s]
NAV_LAT, NAV_LON, NAV_H, NAV_VEL = 0, 1, 2, 3
# sensor correction vector: gyro bias (3) [rad/s], accel bias (3) [m/s^2], gyro scale (3), accel scale (3)
COR_BG, COR_BA, COR_SG, COR_SA = 0, 3, 6, 9
# memory vector: last compensated rate (3) and specific force (3) in b, last dtheta (3), last dv (3),
# last specific force in n (3), last kinematic acceleration in n (3), has_previous flag
MEM_W, MEM_F, MEM_DTH, MEM_DV, MEM_FN, MEM_AN, MEM_VALID = 0, 3, 6, 9, 12, 15, 18
MEM_SIZE = 19
# index vector for the error-state blocks passed to the kernel (-1 = block absent)
IDX_POS, IDX_VEL, IDX_ATT, IDX_BG, IDX_BA, IDX_SG, IDX_SA = 0, 1, 2, 3, 4, 5, 6


@njit(cache=True)
def _add_skew(A, r0, c0, v, scale):
    """A[r0:r0+3, c0:c0+3] += scale * [v x]."""
    A[r0 + 0, c0 + 1] += -scale * v[2]
    A[r0 + 0, c0 + 2] += scale * v[1]
    A[r0 + 1, c0 + 0] += scale * v[2]
    A[r0 + 1, c0 + 2] += -scale * v[0]
    A[r0 + 2, c0 + 0] += -scale * v[1]
    A[r0 + 2, c0 + 1] += scale * v[0]


@njit(cache=True)
def strapdown_batch(t_s, acc_mps2, gyro_rps, i0, i1, t_prev_s, nav, C_nb, corr, mem, A, idx,
                    inv_tau_bg, inv_tau_ba):
    """Integrate samples i0..i1-1 (IMU axes already turned into the filter body frame b).

    nav (6), C_nb (3x3), mem (MEM_SIZE) are updated in place; corr holds the current bias and scale
    estimates used to compensate the raw samples: w = (w~ - b_g) / (1 + s_g), f = (f~ - b_a) / (1 + s_a).
    A (n x n) accumulates F dt of the error-state model (ekf.py) with the block offsets in idx.
    Returns the time of the last integrated sample (t_prev_s if none).
    """
    dth = np.empty(3)
    dv = np.empty(3)
    tmp = np.empty(3)
    tmp2 = np.empty(3)
    zeta = np.empty(3)
    w_ie = np.empty(3)
    w_en = np.empty(3)
    w_in = np.empty(3)
    cor = np.empty(3)
    fn = np.empty(3)
    vmid = np.empty(3)
    M = np.empty((3, 3))
    Cb = np.empty(9)
    Cn = np.empty(9)
    w = np.empty(3)
    f = np.empty(3)
    p_pos, p_vel, p_att, p_bg, p_ba, p_sg, p_sa = idx[0], idx[1], idx[2], idx[3], idx[4], idx[5], idx[6]
    t_last = t_prev_s
    for k in range(i0, i1):
        for j in range(3):
            w[j] = (gyro_rps[k, j] - corr[COR_BG + j]) / (1.0 + corr[COR_SG + j])
            f[j] = (acc_mps2[k, j] - corr[COR_BA + j]) / (1.0 + corr[COR_SA + j])
        if mem[MEM_VALID] == 0.0:
            for j in range(3):
                mem[MEM_W + j] = w[j]
                mem[MEM_F + j] = f[j]
                mem[MEM_DTH + j] = 0.0
                mem[MEM_DV + j] = 0.0
            mem[MEM_VALID] = 1.0
            if not t_s[k] > t_last:
                t_last = t_s[k]
                continue
            # first sample after a start at t_last < t_s[k]: the interval is integrated with this
            # sample held (dropping it would label the state t_s[k] while it is still at t_last)
        dt = t_s[k] - t_last
        if dt <= 0.0:
            continue
        t_last = t_s[k]
        for j in range(3):
            dth[j] = 0.5 * (mem[MEM_W + j] + w[j]) * dt
            dv[j] = 0.5 * (mem[MEM_F + j] + f[j]) * dt
        lat, h = nav[NAV_LAT], nav[NAV_H]
        vN, vE, vD = nav[3], nav[4], nav[5]
        # mid-interval velocity extrapolated with the last kinematic acceleration
        for j in range(3):
            vmid[j] = nav[NAV_VEL + j] + 0.5 * mem[MEM_AN + j] * dt
        rm, rn = radii(lat)
        cl, sl = math.cos(lat), math.sin(lat)
        w_ie[0], w_ie[1], w_ie[2] = OMEGA_IE_RPS * cl, 0.0, -OMEGA_IE_RPS * sl
        w_en[0] = vmid[1] / (rn + h)
        w_en[1] = -vmid[0] / (rm + h)
        w_en[2] = -vmid[1] * sl / cl / (rn + h)
        for j in range(3):
            w_in[j] = w_ie[j] + w_en[j]
            zeta[j] = w_in[j] * dt
        # specific-force increment with rotation and sculling corrections, in b
        cross_into(dth, dv, tmp)
        for j in range(3):
            tmp[j] = dv[j] + 0.5 * tmp[j]
        cross_into(mem[MEM_DTH:MEM_DTH + 3], dv, tmp2)
        for j in range(3):
            tmp[j] += tmp2[j] / 12.0
        cross_into(mem[MEM_DV:MEM_DV + 3], dth, tmp2)
        for j in range(3):
            tmp[j] += tmp2[j] / 12.0
        # to n with the previous attitude and half the frame rotation
        for i in range(3):
            fn[i] = C_nb[i, 0] * tmp[0] + C_nb[i, 1] * tmp[1] + C_nb[i, 2] * tmp[2]
        cross_into(zeta, fn, tmp2)
        for i in range(3):
            fn[i] = fn[i] - 0.5 * tmp2[i]
        g = normal_gravity(lat, h)
        for j in range(3):
            cor[j] = 2.0 * w_ie[j] + w_en[j]
        cross_into(cor, vmid, tmp2)
        v_old0, v_old1, v_old2 = vN, vE, vD
        nav[3] = vN + fn[0] - tmp2[0] * dt
        nav[4] = vE + fn[1] - tmp2[1] * dt
        nav[5] = vD + fn[2] + (g - tmp2[2]) * dt
        for j in range(3):
            mem[MEM_AN + j] = (nav[NAV_VEL + j] - (v_old0, v_old1, v_old2)[j]) / dt
            mem[MEM_FN + j] = fn[j] / dt
        # position, trapezoid on velocity
        vmN = 0.5 * (v_old0 + nav[3])
        vmE = 0.5 * (v_old1 + nav[4])
        vmD = 0.5 * (v_old2 + nav[5])
        h_new = h - vmD * dt
        h_mid = 0.5 * (h + h_new)
        lat_new = lat + vmN / (rm + h_mid) * dt
        lat_mid = 0.5 * (lat + lat_new)
        rm2, rn2 = radii(lat_mid)
        nav[NAV_LON] += vmE / ((rn2 + h_mid) * math.cos(lat_mid)) * dt
        nav[NAV_LAT] = lat_new
        nav[NAV_H] = h_new
        # attitude: body rotation with coning, frame rotation
        cross_into(mem[MEM_DTH:MEM_DTH + 3], dth, tmp2)
        for j in range(3):
            tmp[j] = dth[j] + tmp2[j] / 12.0
        exp_so3_into(tmp[0], tmp[1], tmp[2], Cb)
        exp_so3_into(-zeta[0], -zeta[1], -zeta[2], Cn)
        for i in range(3):
            for j in range(3):
                M[i, j] = C_nb[i, 0] * Cb[j] + C_nb[i, 1] * Cb[3 + j] + C_nb[i, 2] * Cb[6 + j]
        for i in range(3):
            for j in range(3):
                C_nb[i, j] = Cn[3 * i] * M[0, j] + Cn[3 * i + 1] * M[1, j] + Cn[3 * i + 2] * M[2, j]
        for j in range(3):
            mem[MEM_W + j] = w[j]
            mem[MEM_F + j] = f[j]
            mem[MEM_DTH + j] = dth[j]
            mem[MEM_DV + j] = dv[j]

        # error-state dynamics F dt (errors are estimate - truth; ekf.py documents the model)
        for j in range(3):
            A[p_pos + j, p_vel + j] += dt
        _add_skew(A, p_vel, p_vel, cor, -dt)
        for j in range(3):
            fn[j] = mem[MEM_FN + j]
        _add_skew(A, p_vel, p_att, fn, dt)
        A[p_vel + 2, p_pos + 2] += 2.0 * g / (math.sqrt(rm * rn) + h) * dt
        _add_skew(A, p_att, p_att, w_in, -dt)
        for i in range(3):
            for j in range(3):
                A[p_att + i, p_bg + j] += C_nb[i, j] * dt
                A[p_vel + i, p_ba + j] += -C_nb[i, j] * dt
        for j in range(3):
            A[p_bg + j, p_bg + j] += -inv_tau_bg * dt
            A[p_ba + j, p_ba + j] += -inv_tau_ba * dt
        if p_sg >= 0:
            for i in range(3):
                for j in range(3):
                    A[p_att + i, p_sg + j] += C_nb[i, j] * w[j] * dt
        if p_sa >= 0:
            for i in range(3):
                for j in range(3):
                    A[p_vel + i, p_sa + j] += -C_nb[i, j] * f[j] * dt
    return t_last
