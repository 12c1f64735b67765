"""comma2k19 segment folders (Schafer et al. 2018, "A Commute in Data: The comma2k19 Dataset",
arXiv:1812.05752; github.com/commaai/comma2k19).

Every file is a NumPy array (``value`` and ``t``); ``t`` is the device's boot clock [s].

Time mapping: ``global_pose/frame_times`` (boot clock) and ``frame_gps_times`` ([week, TOW]) are
pairs written by the source; boot -> GPS is fitted to them by least squares
(``timebase.fit_clock_least_squares``) and applied to every stream's ``t``.

- IMU: ``processed_log/IMU/accelerometer`` [m/s^2] and ``gyro`` [rad/s] (``gyro_uncalibrated``
  minus the phone's bias estimate), axes already [forward, right, down] = the device frame, so
  ``imu_to_body`` is the identity (the device's small misalignment to the car is not declared).
- GNSS: ``live_gnss_ublox`` [lat deg, lon deg, speed m/s, UTC ms since 1970, altitude m, bearing
  deg]. t_s is the solution's own UTC stamp converted to GPS time (time of validity); the boot
  time of its arrival gives the message latency (``notes["gnss_latency_s"]``). The altitude agrees
  with the reference's ellipsoidal height (not MSL: the geoid undulation there is about -32 m), so
  ``height_datum = "ellipsoidal"``. The stream carries no accuracy and no RTK: fix = SINGLE and the
  sigma is nominal, from the u-blox M8 data sheet's 2.5 m CEP horizontal accuracy
  (sigma = CEP / 1.1774 per horizontal axis) and twice that vertically (an assumption). The 3-D
  velocity is not given: ``vel_ned_mps`` is None; the horizontal velocity from speed and bearing
  is in ``notes["gnss_vel_ne_mps"]``.
- Wheels: ``CAN/wheel_speed`` [FL, FR, RL, RR] m/s -> WheelSpeedData of the mean of the four
  (or of the rear axle); ``CAN/speed`` (the car's speed) -> ``notes["can_speed"]``.
- Reference: ``global_pose`` (20 Hz, the source's INS/GNSS/vision optimiser, pose of the device):
  ECEF positions -> lla (``geo.ecef_to_lla``, ellipsoidal); ECEF velocities -> NED with
  ``C_en`` at each position; quaternions [w, x, y, z] are device -> ECEF rotations
  (``v_ecef = dcm_from_quat(q) @ v_device``, checked on the data: the device x axis follows the
  velocity), so ``C_nb = C_en @ dcm_from_quat(q)`` with b = device frame (x forward, y right,
  z down).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from v2xpos import geo, rotation, timebase
from v2xpos.datasets.issues import ParseIssues
from v2xpos.types import Dataset, FixStatus, GnssData, ImuData, ReferenceTrajectory, WheelSpeedData

CEP_TO_SIGMA = 1.1774
"""CEP = 1.1774 sigma for a circular Gaussian horizontal error."""
UBLOX_M8_CEP_M = 2.5


def _load(folder: Path, rel: str) -> np.ndarray:
    path = folder / rel
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: cannot load numpy array ({exc})") from None


def _stream(folder: Path, rel: str, issues: ParseIssues, width: int | None) -> tuple[np.ndarray, np.ndarray]:
    """(t, value) of one stream; rows with a non-finite time/value or a time not after the previous
    row are dropped and counted (the row index + 1 is reported as the line)."""
    t = _load(folder, f"{rel}/t").astype(float).reshape(-1)
    v = _load(folder, f"{rel}/value").astype(float)
    if v.ndim == 1:
        v = v[:, None]
    if v.shape[0] != t.shape[0] or (width is not None and v.shape[1] != width):
        raise ValueError(f"{folder / rel}: value shape {v.shape} does not match t {t.shape} "
                         f"(expected width {width})")
    ok = np.isfinite(t) & np.all(np.isfinite(v), axis=1)
    run_max = np.maximum.accumulate(np.where(np.isfinite(t), t, -np.inf))
    ok[1:] &= t[1:] > run_max[:-1]
    for i in np.flatnonzero(~ok):
        issues.add(int(i) + 1, f"{rel}: non-finite or non-increasing row")
    return t[ok], v[ok]


def load_comma2k19(folder: str | Path, wheel_mode: str = "mean4",
                   horizontal_cep_m: float = UBLOX_M8_CEP_M) -> Dataset:
    """Load a comma2k19 segment folder -> Dataset (see module doc for every conversion).

    wheel_mode: "mean4" (mean of the four wheels) or "rear" (mean of RL and RR).
    """
    folder = Path(folder)
    if wheel_mode not in ("mean4", "rear"):
        raise ValueError(f"wheel_mode must be 'mean4' or 'rear', got {wheel_mode!r}")
    issues = ParseIssues(str(folder))

    frame_t = _load(folder, "global_pose/frame_times").astype(float).reshape(-1)
    week_tow = _load(folder, "global_pose/frame_gps_times").astype(float)
    frame_gps = timebase.gps_seconds_from_week_tow(week_tow[:, 0], week_tow[:, 1])
    clock = timebase.fit_clock_least_squares(frame_t, frame_gps)

    acc_t, acc = _stream(folder, "processed_log/IMU/accelerometer", issues, 3)
    gyr_t, gyr = _stream(folder, "processed_log/IMU/gyro", issues, 3)
    if not np.array_equal(acc_t, gyr_t):
        gyr = np.column_stack([np.interp(acc_t, gyr_t, gyr[:, k]) for k in range(3)])
    imu = ImuData(t_s=clock.to_gps(acc_t), acc_mps2=acc, gyro_rps=gyr)

    g_t, g = _stream(folder, "processed_log/GNSS/live_gnss_ublox", issues, 6)
    t_valid = timebase.unix_to_gps_seconds(g[:, 3] * 1e-3)
    order_ok = np.ones(t_valid.size, dtype=bool)
    order_ok[1:] = t_valid[1:] > np.maximum.accumulate(t_valid)[:-1]
    for i in np.flatnonzero(~order_ok):
        issues.add(int(i) + 1, "live_gnss_ublox: UTC stamp not after the previous solution")
    g_t, g, t_valid = g_t[order_ok], g[order_ok], t_valid[order_ok]
    n = t_valid.size
    sd_h = horizontal_cep_m / CEP_TO_SIGMA
    gnss = GnssData(t_s=t_valid,
                    lla=np.column_stack([np.radians(g[:, 0]), np.radians(g[:, 1]), g[:, 4]]),
                    fix=np.full(n, int(FixStatus.SINGLE), dtype=np.int8),
                    sd_ned_m=np.tile([sd_h, sd_h, 2.0 * sd_h], (n, 1)),
                    height_datum="ellipsoidal")
    bearing = np.radians(g[:, 5])
    vel_ne = np.column_stack([g[:, 2] * np.cos(bearing), g[:, 2] * np.sin(bearing)])
    latency = clock.to_gps(g_t) - t_valid

    w_t, w = _stream(folder, "processed_log/CAN/wheel_speed", issues, 4)
    speed = w.mean(axis=1) if wheel_mode == "mean4" else w[:, 2:4].mean(axis=1)
    wheel = WheelSpeedData(t_s=clock.to_gps(w_t), speed_mps=speed)
    s_t, s = _stream(folder, "processed_log/CAN/speed", issues, 1)
    can_speed = WheelSpeedData(t_s=clock.to_gps(s_t), speed_mps=s[:, 0])

    pos = _load(folder, "global_pose/frame_positions").astype(float)
    vel = _load(folder, "global_pose/frame_velocities").astype(float)
    quat = _load(folder, "global_pose/frame_orientations").astype(float)
    lla = geo.ecef_to_lla(pos)
    C_en = np.stack([geo.dcm_ecef_to_ned(la, lo) for la, lo in lla[:, :2]])
    v_ned = np.einsum("nij,nj->ni", C_en, vel)
    C_e_device = np.stack([rotation.dcm_from_quat(q / np.linalg.norm(q)) for q in quat])
    C_nb = np.einsum("nij,njk->nik", C_en, C_e_device)
    reference = ReferenceTrajectory(t_s=frame_gps, lla=lla, v_ned_mps=v_ned, C_nb=C_nb)

    notes = {
        "boot_to_gps_clock": clock.as_dict(),
        "gnss_latency_s": {"min": float(latency.min()), "median": float(np.median(latency)),
                           "max": float(latency.max())},
        "gnss_vel_ne_mps": vel_ne,
        "gnss_sd_note": f"nominal: u-blox M8 {horizontal_cep_m} m CEP; no RTK (fix SINGLE)",
        "can_speed": can_speed,
        "wheel_mode": wheel_mode,
        "reference_body_frame": "device (camera housing): x forward, y right, z down",
        "malformed": [issues.as_dict()],
    }
    return Dataset(name=folder.name, platform="car", imu=imu, gnss=gnss, imu_to_body=np.eye(3),
                   lever_arm_m=np.zeros(3), lever_arm_sd_m=0.5, wheel=wheel, reference=reference,
                   malformed_lines=issues.count, source=folder, notes=notes)
