"""Data containers shared along the pipeline: sensor records, datasets, navigation states.

Arrays are column-per-axis numpy arrays; times are GPS seconds since the GPS epoch
(1980-01-06 00:00:00 GPST, no leap seconds) unless a field says otherwise.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path

import numpy as np


class FixStatus(IntEnum):
    """GNSS solution status, ordered from worst to best."""
    NONE = 0
    DEAD_RECKONING = 1
    SINGLE = 2
    DGPS = 3
    FLOAT = 4
    FIXED = 5

    @classmethod
    def from_rtklib_q(cls, q: int) -> "FixStatus":
        """RTKLIB Q flag (1 fix, 2 float, 3 sbas, 4 dgps, 5 single, 6 ppp) -> FixStatus."""
        return _RTKLIB_Q.get(int(q), cls.NONE)

    @property
    def is_rtk(self) -> bool:
        """True for RTK fixed or float: the only statuses a relative pair may be valid on."""
        return self in (FixStatus.FIXED, FixStatus.FLOAT)


_RTKLIB_Q = {1: FixStatus.FIXED, 2: FixStatus.FLOAT, 3: FixStatus.DGPS, 4: FixStatus.DGPS,
             5: FixStatus.SINGLE, 6: FixStatus.SINGLE}


@dataclass
class ImuData:
    """IMU samples in the IMU's own axes.

    t_s: GPS time of validity of each sample [s]; acc_mps2: specific force [m/s^2];
    gyro_rps: angular rate [rad/s]. counter_ms: the device counter when the source has one.
    """
    t_s: np.ndarray
    acc_mps2: np.ndarray
    gyro_rps: np.ndarray
    counter_ms: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.t_s)


@dataclass
class GnssData:
    """GNSS solutions at the antenna.

    lla: (lat_rad, lon_rad, h_m ellipsoidal); fix: FixStatus values; sd_ned_m: 1-sigma per NED axis;
    vel_ned_mps / vel_sd_ned_mps: velocity and its 1-sigma when the source gives it (else None).
    height_datum: "ellipsoidal" or "msl" (the source's height is above mean sea level, as given).
    """
    t_s: np.ndarray
    lla: np.ndarray
    fix: np.ndarray
    sd_ned_m: np.ndarray
    vel_ned_mps: np.ndarray | None = None
    vel_sd_ned_mps: np.ndarray | None = None
    height_datum: str = "ellipsoidal"

    def __len__(self) -> int:
        return len(self.t_s)


@dataclass
class WheelSpeedData:
    """Vehicle forward speed from wheel odometry [m/s] at GPS times t_s."""
    t_s: np.ndarray
    speed_mps: np.ndarray


@dataclass
class ReferenceTrajectory:
    """Independent reference solution: t_s, lla (rad, m); optional v_ned_mps, C_nb (N,3,3)."""
    t_s: np.ndarray
    lla: np.ndarray
    v_ned_mps: np.ndarray | None = None
    C_nb: np.ndarray | None = None


@dataclass
class Dataset:
    """One recording with what was declared about it.

    imu_to_body: nominal DCM, ``v_body = imu_to_body @ v_imu`` (body x forward, y right, z down).
    lever_arm_m: antenna relative to the IMU in the body frame [forward, right, down].
    malformed_lines: input records skipped by the readers (counted, never fatal).
    """
    name: str
    platform: str
    imu: ImuData
    gnss: GnssData
    imu_to_body: np.ndarray = field(default_factory=lambda: np.eye(3))
    lever_arm_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    lever_arm_sd_m: float = 0.1
    wheel: WheelSpeedData | None = None
    reference: ReferenceTrajectory | None = None
    malformed_lines: int = 0
    source: Path | None = None
    notes: dict = field(default_factory=dict)
    calibration: object | None = None
    """``v2xpos.datasets.calibration.CalibrationTable`` from the descriptor's ``[calibration]``
    table (estimated effects to apply), or None."""
    verification: object | None = None
    """``v2xpos.datasets.verification.VerificationRecord`` from the descriptor's ``[verification]``
    table (the set-up verified on an earlier drive), or None."""



class FilterReason(IntEnum):
    """Why a vehicle's navigation solution is not verified (``NavState.reason``); ``OK`` when it is.

    The filter sets the first that applies in this order; services carry it on the wire, in the
    status and in ``results.csv``, and the monitor turns it into an instruction for the operator.
    """
    OK = 0
    ALIGNING = 1                  # the filter has not started (no GNSS fix yet, or re-aligning)
    HEADING_PENDING = 2           # started at a standstill: the heading is open until the vehicle drives off
    COASTING = 3                  # no GNSS position used for longer than the filter's coast limit
    TIME_OFFSET_CONVERGING = 4    # the IMU time offset is not yet known well enough for the limit
    SETUP_UNVERIFIED = 5          # an undeclared set-up error (lever arm, mounting) not yet excluded: drive a turn
    PROTECTION_EXCEEDED = 6       # the protection level is above its limit for another reason
    TEST_POSITION = 7             # the GNSS position innovations failed the consistency test
    TEST_VELOCITY = 8             # the GNSS velocity innovations failed the consistency test
    TEST_SEPARATION = 9           # the solution-separation (fault) test failed
    RECEIVER_FLOAT = 10           # the receiver is not RTK fixed (float or worse)


@dataclass
class NavState:
    """Navigation solution of one vehicle at GPS time t_s.

    lla (rad, m) of the vehicle reference point (IMU); v_ned_mps; acc_body_mps2 (kinematic
    acceleration, gravity removed) and rate_body_rps in body axes; rpy_rad = (roll, pitch, yaw) of
    C_nb; *_sd are 1-sigma per axis (pos_sd_m / vel_sd_mps per NED axis; att_sd_rad of the small
    attitude error about the N, E, D axes, which for a level vehicle is roll, pitch, yaw error only
    when it heads north -- the D component is the yaw error at any heading); fix is the GNSS status
    behind the solution.
    """
    t_s: float
    lla: np.ndarray
    v_ned_mps: np.ndarray
    acc_body_mps2: np.ndarray
    rate_body_rps: np.ndarray
    rpy_rad: np.ndarray
    pos_sd_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    vel_sd_mps: np.ndarray = field(default_factory=lambda: np.zeros(3))
    att_sd_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))
    fix: FixStatus = FixStatus.NONE
    attitude_ok: bool = True
    """False while the filter's attitude is not determined (heading pending at a standstill start)."""
    pos_corr: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """Correlation coefficients (NE, ND, ED) of the position error (0: uncorrelated axes)."""
    consistent: bool = True
    """False after the filter's own consistency test (block NIS, body-frame innovation mean or
    solution separation, ``v2xpos.ins.consistency``) failed, until consecutive quiet blocks release it."""
    verified: bool = True
    """False while the protection level of the filter's solution-separation test against an
    undeclared horizontal lever arm is above its limit (``consistency.FaultTolerantSolution``)."""
    reason: FilterReason = FilterReason.OK
    """Why the solution is not verified (``FilterReason``; OK when it is)."""
    protection_m: float = float("nan")
    """Horizontal protection level [m] of the solution at the integrity risk of its configuration
    (NaN when the filter computes none)."""


@dataclass
class LocalReference:
    """Reference trajectory known only in a local frame (no absolute position).

    t_s: times on the recording's own axis [s]; pos_ned_m: position in a local NED frame about the
    source's origin [m]; rpy_rad: (roll, pitch, yaw) of C_nb [rad]; speed_mps optional.
    """
    t_s: np.ndarray
    pos_ned_m: np.ndarray
    rpy_rad: np.ndarray
    speed_mps: np.ndarray | None = None


@dataclass
class MultiImuRecording:
    """Several IMU units on one rigid body, for grading them against each other.

    units: name -> ImuData in each unit's own axes; unit_euler_rad: name -> (N,3) Euler angles the
    unit itself reports (its own convention, see the reader); reference: the platform's reference
    trajectory when the source has one. Times are on the recording's own axis unless
    ``time_scale`` says "gps".
    """
    name: str
    units: dict[str, ImuData]
    unit_euler_rad: dict[str, np.ndarray] = field(default_factory=dict)
    reference: LocalReference | ReferenceTrajectory | None = None
    time_scale: str = "recording"
    malformed_lines: int = 0
    source: Path | None = None
    notes: dict = field(default_factory=dict)
