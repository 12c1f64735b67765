"""IMU grading: time sync, the rotation between units, window consistency (RMSE / PCC),
fused-solution differences, bias stability between stops, pose-aided rate check, verdict; one
vehicle's units against each other (``unit_comparison``, ``grader``), a multi-IMU recording
(``recording``). Public API::

    from v2xpos.quality import grade_units, VehicleGrader, Thresholds, GradeConfig
    report = grade_units({"imu1": imu_a, "imu2": imu_b, "imu3": imu_c})
    g = VehicleGrader(["imu1", "imu2", "imu3"]); g.add("imu1", t_s, gyro_rps, acc_mps2); g.grades()

Methods, equations and thresholds: docs/quality.md.
"""
from .unit_comparison import GradeConfig
from .grader import UnitGrader, VehicleGrader, grade_units, public_report
from .verdict import Thresholds

__all__ = ["grade_units", "public_report", "VehicleGrader", "UnitGrader", "Thresholds", "GradeConfig"]
