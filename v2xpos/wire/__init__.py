"""V2V wire format: versioned, validated msgpack messages (schema in docs/protocol.md).

Modules: ``keys`` (key expressions), ``envelope`` (outer frame, signing hook), ``fields`` (field
limits, ``WireError`` and the validated field readers), ``state`` (``StateMessage``, ``Geometry``
and their codec), ``relative`` (``RelativeResult``, ``TargetStatus``, ``FixSide`` and their
codec), ``imu_stream`` (the grading's IMU stream). Every public name is importable from
``v2xpos.wire`` itself.

Public API (stable)
-------------------
* ``SCHEMA_VERSION``, ``ENVELOPE_VERSION``, ``MAX_MESSAGE_BYTES``, ``MAX_GEOMETRY_POINTS``
* key expressions, every one the project uses: ``state_key(fleet, vehicle_id)``,
  ``STATE_KEY_ALL(fleet)`` (``v2xpos/<fleet>/vehicle/*/state``), ``relative_key(fleet, master_id)``,
  ``imu_key(fleet, vehicle_id)``, ``status_key`` and ``grades_key``
  (fleet, master_id), ``clock_key(fleet)`` and ``ready_key(fleet, vehicle_id)`` (session clock),
  ``corrections_key(fleet)``
* the IMU stream of the grading: ``encode_imu_payload``, ``decode_imu_payload`` -> ``ImuPayload``
* ``WireError(reason, field)`` -- every malformed input raises this, never anything else.
* ``Geometry`` -- target outline in its own body frame (points, polygon or circle).
* ``StateMessage`` -- one vehicle/pedestrian state; ``encode_state(msg, sign=None) -> bytes``,
  ``decode_state(data) -> StateMessage``.
* ``TargetStatus`` (VALID, FIX_INVALID, TIMEOUT, NO_DATA, FUTURE and the kinematic-but-not-valid
  statuses of ``KINEMATIC_STATUSES``), ``FixSide`` (which side's fix failed the gate) and
  ``RelativeResult`` -- what the master republishes; ``encode_relative(res, sign=None) -> bytes``
  (always ``RELATIVE_SCHEMA_VERSION``), ``decode_relative(data) -> RelativeResult`` (versions in
  ``RELATIVE_SCHEMA_VERSIONS``: 1 = before the vehicles' fix states and the yaw sigma, decoded with
  ``master_fix``/``target_fix`` NONE and ``rel_yaw_sd_rad`` NaN).
* Envelope helpers for signing: ``pack_envelope(body, sig, key_id)``, ``unpack_envelope(data)
  -> Envelope``.

Envelope and signing
--------------------
Every datagram is a msgpack array ``[ENVELOPE_VERSION, body, sig, key_id]``: ``body`` is the
msgpack-encoded message map as a *bin* value -- exactly the byte string that is signed
(Ed25519 over ``body``); ``sig`` is bin or nil, ``key_id`` str or nil. ``decode_state`` keeps
``body`` in ``StateMessage.signed_payload`` so a verifier checks ``sig`` over it without
re-encoding. ``sign`` arguments are callables ``body -> (sig_bytes, key_id)``.

Frames and units: positions geodetic (lat/lon rad, ellipsoidal height m); velocity NED [m/s];
acceleration (kinematic, gravity removed) and angular rate in the vehicle body frame
(x forward, y right, z down) [m/s^2, rad/s]; attitude Z-Y-X Euler (roll, pitch, yaw) of C_nb
[rad]; standard deviations are 1-sigma per axis.
"""
from __future__ import annotations

from .keys import (STATE_KEY_ALL, VEHICLE_STATUS_KEY_ALL, alive_key, vehicle_status_key, clock_key, corrections_key, grades_key, imu_key, ready_key, relative_key,
                   state_key, status_key)
from .envelope import (ENVELOPE_VERSION, MAX_MESSAGE_BYTES, Envelope, Signer, pack_envelope, unpack_envelope)
from .fields import (KINDS, MAX_ACC_MPS2, MAX_GEOMETRY_M, MAX_GEOMETRY_POINTS, MAX_HEIGHT_M, MAX_ID_CHARS,
                     MAX_RATE_RPS, MAX_SD, MAX_SPEED_MPS, MAX_T_GPS_S, MAX_UINT64, MIN_HEIGHT_M, WireError)
from .state import (GEOMETRY_KINDS, SCHEMA_VERSION, STATE_FLAG_ATTITUDE_UNDETERMINED, STATE_FLAG_INCONSISTENT,
                    STATE_FLAG_TIME_UNSYNCED, STATE_FLAG_UNVERIFIED, Geometry, StateMessage, decode_state,
                    decode_state_body, encode_state, encode_state_body)
from .relative import (KINEMATIC_STATUSES, RELATIVE_SCHEMA_VERSION, RELATIVE_SCHEMA_VERSIONS, FixSide,
                       RelativeResult, TargetStatus, decode_relative, decode_relative_body, encode_relative,
                       encode_relative_body, reason_name, reason_text)
from .imu_stream import (IMU_PAYLOAD_VERSION, MAX_IMU_ROWS, MAX_IMU_UNITS, ImuPayload, ImuPayloadError,
                         decode_imu_payload, encode_imu_payload)

__all__ = ["SCHEMA_VERSION", "RELATIVE_SCHEMA_VERSION", "RELATIVE_SCHEMA_VERSIONS", "ENVELOPE_VERSION",
           "MAX_MESSAGE_BYTES", "MAX_GEOMETRY_POINTS", "MAX_ID_CHARS", "MAX_SPEED_MPS", "MAX_ACC_MPS2",
           "MAX_RATE_RPS", "MAX_HEIGHT_M", "MIN_HEIGHT_M", "MAX_SD", "MAX_GEOMETRY_M", "MAX_T_GPS_S",
           "MAX_UINT64", "STATE_FLAG_ATTITUDE_UNDETERMINED", "STATE_FLAG_TIME_UNSYNCED",
           "STATE_FLAG_INCONSISTENT", "STATE_FLAG_UNVERIFIED", "KINDS", "GEOMETRY_KINDS", "Signer", "state_key",
           "STATE_KEY_ALL", "relative_key", "imu_key", "status_key", "grades_key", "clock_key", "ready_key",
           "corrections_key", "WireError", "TargetStatus", "KINEMATIC_STATUSES", "FixSide", "Geometry",
           "StateMessage", "RelativeResult", "Envelope", "pack_envelope", "encode_state_body", "encode_state",
           "encode_relative_body", "encode_relative", "unpack_envelope", "decode_state_body", "decode_state",
           "decode_relative_body", "decode_relative", "IMU_PAYLOAD_VERSION", "MAX_IMU_ROWS", "MAX_IMU_UNITS",
           "ImuPayloadError", "ImuPayload", "encode_imu_payload", "decode_imu_payload",
           "reason_name", "reason_text", "VEHICLE_STATUS_KEY_ALL", "vehicle_status_key", "alive_key"]
