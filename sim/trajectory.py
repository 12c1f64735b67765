"""Truth trajectories for land vehicles and pedestrians, with the ideal IMU outputs they imply.

The vehicle moves along its body x axis (no side-slip) with speed s, heading (yaw) psi and path
pitch theta; body roll follows lateral acceleration (``roll_per_lat_acc_rad``). Controls
(longitudinal acceleration, yaw rate, pitch) are piecewise constant per ``Segment`` and pass a
first-order lag of time constant ``smooth_tau_s`` so that jerk stays finite, as on a real car.

Kinematics are integrated in the local-level NED frame on the WGS84 ellipsoid, and the ideal
inertial measurements follow from the NED mechanization equations (Groves 2013 eqs. 5.44-5.54):

    v_n = s [cos(theta) cos(psi), cos(theta) sin(psi), -sin(theta)]
    f_b   = C_bn (dv_n/dt + (2 w_ie^n + w_en^n) x v_n - g^n)
    w_ib^b = w_nb^b + C_bn (w_ie^n + w_en^n)
    w_nb^b = [phi' - psi' sin(theta), theta' cos(phi) + psi' cos(theta) sin(phi),
              -theta' sin(phi) + psi' cos(theta) cos(phi)]          (Euler kinematics, Z-Y-X)

so a mechanization fed with these samples reproduces the trajectory up to its own integration
error. Frames: NED local level; body x forward, y right, z down; ``C_nb`` body -> NED.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from v2xpos import geo
from v2xpos.rotation import dcm_from_euler_batch


@dataclass
class Segment:
    """One manoeuvre: for ``duration_s`` hold longitudinal ``accel_mps2`` and ``yaw_rate_rps``;
    ``pitch_rad`` (road grade, + nose up) if given, else keep the current pitch."""
    duration_s: float
    accel_mps2: float = 0.0
    yaw_rate_rps: float = 0.0
    pitch_rad: float | None = None


@dataclass
class Trajectory:
    """Sampled truth. Arrays are (N,) or (N, 3); lla in (rad, rad, m); r_ned_m relative to lla0."""
    t_s: np.ndarray
    lla: np.ndarray
    r_ned_m: np.ndarray
    v_ned_mps: np.ndarray
    a_ned_mps2: np.ndarray
    rpy_rad: np.ndarray
    C_nb: np.ndarray
    w_nb_b_rps: np.ndarray
    w_ib_b_rps: np.ndarray
    f_b_mps2: np.ndarray
    speed_mps: np.ndarray
    lla0: np.ndarray
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.t_s)

    @property
    def dt_s(self) -> float:
        return float(self.t_s[1] - self.t_s[0])

    @property
    def acc_body_mps2(self) -> np.ndarray:
        """Kinematic acceleration dv_n/dt resolved in the body frame, C_bn a_n."""
        return np.einsum("nji,nj->ni", self.C_nb, self.a_ned_mps2)

    def index_at(self, t_s: float) -> int:
        """Index of the last sample at or before t_s (clipped to the trajectory)."""
        return int(np.clip(np.searchsorted(self.t_s, t_s, side="right") - 1, 0, len(self.t_s) - 1))

    def sample(self, t_s: np.ndarray | float) -> dict:
        """Truth interpolated linearly at arbitrary times (NED position, velocity, acceleration,
        body rate, attitude via unwrapped Euler angles). Returns a dict of arrays."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        out = {}
        for name in ("r_ned_m", "v_ned_mps", "a_ned_mps2", "w_nb_b_rps", "w_ib_b_rps", "f_b_mps2"):
            arr = getattr(self, name)
            out[name] = np.stack([np.interp(t, self.t_s, arr[:, k]) for k in range(3)], axis=1)
        rpy_u = np.unwrap(self.rpy_rad, axis=0)
        rpy = np.stack([np.interp(t, self.t_s, rpy_u[:, k]) for k in range(3)], axis=1)
        out["rpy_rad"] = (rpy + np.pi) % (2 * np.pi) - np.pi
        out["C_nb"] = dcm_from_euler_batch(out["rpy_rad"])
        out["lla"] = geo.ned_to_lla(out["r_ned_m"], self.lla0)
        out["acc_body_mps2"] = np.einsum("nji,nj->ni", out["C_nb"], out["a_ned_mps2"])
        return out

    def shifted(self, dt_s: float) -> "Trajectory":
        """The same trajectory with every time stamp moved by dt_s (for a follower in a convoy)."""
        return Trajectory(**{**self.__dict__, "t_s": self.t_s + dt_s})


def _lag(u: np.ndarray, dt_s: float, tau_s: float) -> np.ndarray:
    """First-order lag y' = (u - y)/tau, exact discretisation, y(0) = u(0)."""
    if tau_s <= 0:
        return u.copy()
    a = np.exp(-dt_s / tau_s)
    y = np.empty_like(u)
    y[0] = u[0]
    for k in range(1, len(u)):
        y[k] = a * y[k - 1] + (1 - a) * u[k]
    return y


def generate(segments: list[Segment], dt_s: float = 0.01, lla0: np.ndarray | None = None,
             speed0_mps: float = 0.0, yaw0_rad: float = 0.0, pitch0_rad: float = 0.0,
             t0_s: float = 1.4e9, smooth_tau_s: float = 0.3, roll_per_lat_acc_rad: float = 0.006,
             r0_ned_m: np.ndarray | None = None) -> Trajectory:
    """Integrate a segment list into a truth trajectory sampled every dt_s.

    lla0: origin of ``r_ned_m`` (default 40 deg N, 105 deg W, 1600 m); r0_ned_m: start position
    relative to lla0. t0_s: GPS seconds of the first sample.
    """
    lla0 = np.array([np.radians(40.0), np.radians(-105.0), 1600.0]) if lla0 is None else np.asarray(lla0, float)
    n = int(round(sum(s.duration_s for s in segments) / dt_s)) + 1
    acc_cmd = np.zeros(n)
    yr_cmd = np.zeros(n)
    pitch_cmd = np.full(n, pitch0_rad)
    k0 = 0
    pitch_now = pitch0_rad
    for seg in segments:
        k1 = min(n, k0 + int(round(seg.duration_s / dt_s)))
        if k1 > k0:
            # the segment's speed change accel x duration is kept on the sample grid: its held
            # acceleration is scaled by duration / (samples x dt). Rounding the duration alone
            # changed the speed by up to accel x dt / 2 per segment (1.25 cm/s at 2.5 m/s^2), so a
            # "stop" reached after such changes crept at ~1 cm/s with the engine off
            acc_cmd[k0:k1] = seg.accel_mps2 * seg.duration_s / ((k1 - k0) * dt_s)
        yr_cmd[k0:k1] = seg.yaw_rate_rps
        if seg.pitch_rad is not None:
            pitch_now = seg.pitch_rad
        pitch_cmd[k0:k1] = pitch_now
        k0 = k1
    if k0 < n:
        pitch_cmd[k0:] = pitch_now
    acc = _lag(acc_cmd, dt_s, smooth_tau_s)
    yr = _lag(yr_cmd, dt_s, smooth_tau_s)
    theta = _lag(pitch_cmd, dt_s, max(smooth_tau_s, 1.0))

    # speed and heading: trapezoid integration, speed clamped at zero (a car stops, it does not reverse)
    s = np.empty(n)
    s[0] = speed0_mps
    for k in range(1, n):
        s[k] = max(0.0, s[k - 1] + 0.5 * (acc[k - 1] + acc[k]) * dt_s)
    acc = np.gradient(s, dt_s) if n > 2 else acc
    psi = yaw0_rad + np.concatenate([[0.0], np.cumsum(0.5 * (yr[1:] + yr[:-1]) * dt_s)])
    theta_dot = np.gradient(theta, dt_s)

    cps, sps, cth, sth = np.cos(psi), np.sin(psi), np.cos(theta), np.sin(theta)
    u = np.stack([cth * cps, cth * sps, -sth], axis=1)
    du_dpsi = np.stack([-cth * sps, cth * cps, np.zeros(n)], axis=1)
    du_dth = np.stack([-sth * cps, -sth * sps, -cth], axis=1)
    v = s[:, None] * u
    a = acc[:, None] * u + s[:, None] * (du_dpsi * yr[:, None] + du_dth * theta_dot[:, None])

    lat_acc = s * yr * cth
    phi = roll_per_lat_acc_rad * lat_acc
    phi_dot = np.gradient(phi, dt_s)

    # curvilinear position on the ellipsoid (Groves eq. 5.56), trapezoid
    lla = np.empty((n, 3))
    r_start = np.zeros(3) if r0_ned_m is None else np.asarray(r0_ned_m, float)
    lla[0] = geo.ned_to_lla(r_start, lla0)
    for k in range(1, n):
        lat, h = lla[k - 1, 0], lla[k - 1, 2]
        r_m, r_n = geo.radii_m(lat)
        vm = 0.5 * (v[k - 1] + v[k])
        lla[k, 0] = lat + vm[0] / (r_m + h) * dt_s
        lla[k, 1] = lla[k - 1, 1] + vm[1] / ((r_n + h) * np.cos(lat)) * dt_s
        lla[k, 2] = h - vm[2] * dt_s

    rpy = np.stack([phi, theta, (psi + np.pi) % (2 * np.pi) - np.pi], axis=1)
    C_nb = dcm_from_euler_batch(rpy)
    w_nb_b = np.stack([phi_dot - yr * sth,
                       theta_dot * np.cos(phi) + yr * cth * np.sin(phi),
                       -theta_dot * np.sin(phi) + yr * cth * np.cos(phi)], axis=1)
    lat, h = lla[:, 0], lla[:, 2]
    r_m, r_n = geo.radii_m(lat)
    w_ie = np.stack([geo.OMEGA_IE_RPS * np.cos(lat), np.zeros(n), -geo.OMEGA_IE_RPS * np.sin(lat)], axis=1)
    w_en = np.stack([v[:, 1] / (r_n + h), -v[:, 0] / (r_m + h), -v[:, 1] * np.tan(lat) / (r_n + h)], axis=1)
    g = np.zeros((n, 3))
    g[:, 2] = geo.normal_gravity_mps2(lat, h)
    f_n = a + np.cross(2 * w_ie + w_en, v) - g
    f_b = np.einsum("nji,nj->ni", C_nb, f_n)
    w_ib_b = w_nb_b + np.einsum("nji,nj->ni", C_nb, w_ie + w_en)
    r_ned = geo.lla_to_ned(lla, lla0)
    t = t0_s + dt_s * np.arange(n)
    return Trajectory(t_s=t, lla=lla, r_ned_m=r_ned, v_ned_mps=v, a_ned_mps2=a, rpy_rad=rpy, C_nb=C_nb,
                      w_nb_b_rps=w_nb_b, w_ib_b_rps=w_ib_b, f_b_mps2=f_b, speed_mps=s, lla0=lla0)


def static(duration_s: float, dt_s: float = 0.01, **kw) -> Trajectory:
    """A vehicle standing still for duration_s."""
    return generate([Segment(duration_s)], dt_s=dt_s, speed0_mps=0.0, **kw)


def urban_drive(duration_s: float = 120.0, dt_s: float = 0.01, speed_mps: float = 15.0,
                seed: int | None = 0, **kw) -> Trajectory:
    """A drive with a standstill start, accelerations, curves both ways and braking to a stop.

    With ``seed`` the order and size of the manoeuvres vary; the sequence always starts with 10 s
    static (for alignment) and ends stopped.
    """
    rng = np.random.default_rng(seed)
    segs = [Segment(10.0), Segment(speed_mps / 2.0, accel_mps2=2.0)]
    t = sum(x.duration_s for x in segs)
    while t < duration_s - 15.0:
        kind = rng.choice(["straight", "left", "right", "brake"], p=[0.3, 0.3, 0.3, 0.1])
        d = float(rng.uniform(4.0, 10.0))
        if kind == "straight":
            segs.append(Segment(d))
        elif kind in ("left", "right"):
            rate = float(rng.uniform(0.1, 0.3)) * (-1 if kind == "left" else 1)
            segs.append(Segment(d, yaw_rate_rps=rate))
        else:
            segs += [Segment(2.0, accel_mps2=-3.0), Segment(2.0, accel_mps2=3.0)]
            d = 4.0
        t += d
    segs += [Segment(speed_mps / 3.0, accel_mps2=-3.0), Segment(5.0)]
    return generate(segs, dt_s=dt_s, **kw)


def speed_change_drive(duration_s: float = 300.0, dt_s: float = 0.01, accel_mps2: float = 1.5,
                       speed_range_mps: tuple[float, float] = (4.0, 19.0), seed: int | None = 0,
                       **kw) -> Trajectory:
    """A drive whose cruise speed keeps changing: 10 s static, then alternately a speed change at
    +-``accel_mps2`` to a random speed in ``speed_range_mps`` and a straight or curve (yaw rate
    0.05-0.2 rad/s) of 4-10 s; ends braking to a stop. The speed changes make a time offset
    (position error v * tau) distinguishable from a forward lever arm (constant)."""
    rng = np.random.default_rng(seed)
    lo, hi = speed_range_mps
    v = lo + (hi - lo) / 8.0          # first cruise speed, just above the lowest
    segs = [Segment(10.0), Segment(v / accel_mps2, accel_mps2=accel_mps2)]
    t = sum(s.duration_s for s in segs)
    while t < duration_s - 20.0:
        target = float(rng.uniform(lo, hi))
        d = abs(target - v) / accel_mps2
        segs.append(Segment(d, accel_mps2=float(np.sign(target - v)) * accel_mps2))
        v = target
        kind = rng.choice(["straight", "left", "right"])
        hold = float(rng.uniform(4.0, 10.0))
        rate = 0.0 if kind == "straight" else float(rng.uniform(0.05, 0.2)) * (-1 if kind == "left" else 1)
        segs.append(Segment(hold, yaw_rate_rps=rate))
        t += d + hold
    segs += [Segment(v / accel_mps2, accel_mps2=-accel_mps2), Segment(5.0)]
    return generate(segs, dt_s=dt_s, **kw)


def figure_eight_drive(duration_s: float = 300.0, dt_s: float = 0.01,
                       speeds_mps: tuple = (6.0, 12.0, 9.0, 15.0, 7.5, 13.5), max_lat_acc_mps2: float = 4.0,
                       accel_mps2: float = 1.5, **kw) -> Trajectory:
    """A calibration drive: 10 s static, then figure-eights (a left and a right circle) at speeds
    that change between eights (straight at +-``accel_mps2``); each circle's radius is the larger
    of 20 m and ``v^2 / max_lat_acc_mps2``. Turning at several speeds separates the effects that
    a lateral-velocity residual shows as ``v w tau`` (time offset) from those it shows as ``w l``
    (forward lever arm), which a drive at one speed confounds."""
    v = 0.0
    segs = [Segment(10.0)]
    t = 10.0
    k = 0
    while t < duration_s - 20.0:
        target = float(speeds_mps[k % len(speeds_mps)])
        k += 1
        d = max(abs(target - v) / accel_mps2, 2.0)
        segs.append(Segment(d, accel_mps2=(target - v) / d))
        v = target
        radius = max(20.0, v * v / max_lat_acc_mps2)
        w = v / radius
        circle = 2.0 * np.pi / w
        segs += [Segment(circle, yaw_rate_rps=-w), Segment(circle, yaw_rate_rps=w)]
        t += d + 2.0 * circle
    segs += [Segment(v / accel_mps2, accel_mps2=-accel_mps2), Segment(5.0)]
    return generate(segs, dt_s=dt_s, **kw)
