"""Zenoh key expressions of every message the project publishes (``v2xpos/<fleet>/...``).

Vehicles publish under ``vehicle/<id>/`` (state, IMU stream), masters under ``master/<id>/``
(relative results, status, grades), the session clock and readiness under ``session/``, the GNSS
corrections at the fleet's root. docs/protocol.md lists them with their payloads.
"""
from __future__ import annotations


def state_key(fleet: str, vehicle_id: str) -> str:
    """Zenoh key expression a slave publishes its StateMessage on."""
    return f"v2xpos/{fleet}/vehicle/{vehicle_id}/state"


def STATE_KEY_ALL(fleet: str) -> str:  # noqa: N802 (reads as a constant pattern)
    """Key expression matching every vehicle's state in a fleet."""
    return f"v2xpos/{fleet}/vehicle/*/state"


def vehicle_status_key(fleet: str, vehicle_id: str) -> str:
    """Key on which a vehicle service publishes its live status at 1 Hz (JSON,
    ``v2xpos.sources.status``)."""
    return f"v2xpos/{fleet}/vehicle/{vehicle_id}/status"


def VEHICLE_STATUS_KEY_ALL(fleet: str) -> str:  # noqa: N802 (reads as a constant pattern)
    """Key expression matching every vehicle's live status in a fleet."""
    return f"v2xpos/{fleet}/vehicle/*/status"


def alive_key(fleet: str, role: str, ident: str) -> str:
    """Zenoh liveliness token of a running service: ``role`` "master" or "vehicle" (a slave); it
    goes when the service's session closes, also when the process is killed."""
    return f"v2xpos/{fleet}/{role}/{ident}/alive"


def relative_key(fleet: str, master_id: str) -> str:
    """Zenoh key expression a master republishes its RelativeResult messages on."""
    return f"v2xpos/{fleet}/master/{master_id}/relative"


def imu_key(fleet: str, vehicle_id: str) -> str:
    """Zenoh key expression for IMU samples used by IMU grading."""
    return f"v2xpos/{fleet}/vehicle/{vehicle_id}/imu"


def status_key(fleet: str, master_id: str) -> str:
    """Key on which a master publishes its periodic status (JSON, for monitors and the demo table)."""
    return f"v2xpos/{fleet}/master/{master_id}/status"


def grades_key(fleet: str, master_id: str) -> str:
    """Key on which a master publishes IMU grades (JSON)."""
    return f"v2xpos/{fleet}/master/{master_id}/grades"


def clock_key(fleet: str) -> str:
    """Key of the session clock published by a recording master."""
    return f"v2xpos/{fleet}/session/clock"


def ready_key(fleet: str, vehicle_id: str) -> str:
    """Key on which a recording slave says it is ready for the session clock."""
    return f"v2xpos/{fleet}/session/ready/{vehicle_id}"


def corrections_key(fleet: str) -> str:
    """Zenoh key of a fleet's GNSS correction stream."""
    return f"v2xpos/{fleet}/corrections"
