"""The ``[verification]`` table of a dataset descriptor or a vehicle config: a set-up (antenna lever
arm, IMU mounting, and the effects of a ``[calibration]`` table) verified on an earlier drive.

A vehicle's filter carries the hypothesis that its declared set-up is wrong (``v2xpos.ins.integrity``)
with a prior probability: that of a blunder for a set-up never checked, that of a change since for
one verified before (``InsConfig.integrity.setup_fault_prior`` / ``setup_change_prior``). A lever-arm error
shows only when the vehicle turns, so an unverified vehicle is vouched for only after its first
turns; a verified one from its first metres. The record says what was verified, on which drive,
to which protection level::

    [verification]
    verified = true
    drive = "convoy_dev/B/dataset.toml"        # the recording (or session) that verified it
    date = "2026-11-27"                         # when (ISO 8601)
    protection_m = 0.11                         # the horizontal protection level at the end of it
    alert_limit_m = 0.30                        # against this alert limit
    software = "v2xpos 0.1.0 (git 1a2b3c4)"     # optional

Written by ``v2xpos calibrate --write-dataset`` (the calibrated set-up replayed through the
services' filter) and by a service at the end of a session when its config asks for it; read by
``v2xpos.ins.calibrated.ins_config``. A failed consistency test re-opens it for the rest of the
drive (``InsFilter._on_inconsistency``). Unknown keys are rejected with the table and the key named.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

KEYS = ("verified", "drive", "date", "protection_m", "alert_limit_m", "software")


class VerificationError(ValueError):
    """A ``[verification]`` table that cannot be used; the message names where and the key."""


@dataclass
class VerificationRecord:
    """A parsed ``[verification]`` table (see the module docstring)."""
    verified: bool
    drive: str = ""
    date: str = ""
    protection_m: float = math.nan
    alert_limit_m: float = math.nan
    software: str | None = None

    def to_toml(self) -> str:
        """The table as TOML text (``[verification]`` header included), parseable by
        :func:`parse_verification`."""
        import tomli_w
        body = {"verified": bool(self.verified), "drive": self.drive, "date": self.date}
        for key in ("protection_m", "alert_limit_m"):
            v = getattr(self, key)
            if math.isfinite(v):
                body[key] = round(float(v), 4)
        if self.software:
            body["software"] = self.software
        return tomli_w.dumps({"verification": body})


def parse_verification(table: Any, where: str) -> VerificationRecord:
    """A ``VerificationRecord`` from the TOML table ``table``; VerificationError naming ``where``."""
    from v2xpos.schema import check_keys
    if not isinstance(table, dict):
        raise VerificationError(f"{where}: expected a table")
    check_keys(table, KEYS, where, VerificationError)
    if not isinstance(table.get("verified"), bool):
        raise VerificationError(f"{where}.verified: required: true or false")
    out = VerificationRecord(verified=table["verified"])
    for key in ("drive", "date", "software"):
        v = table.get(key)
        if v is not None and not isinstance(v, str):
            raise VerificationError(f"{where}.{key}: expected a string, got {v!r}")
        if v is not None:
            setattr(out, key, v)
    for key in ("protection_m", "alert_limit_m"):
        v = table.get(key)
        if v is None:
            continue
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)) or float(v) < 0:
            raise VerificationError(f"{where}.{key}: expected a number >= 0 [m], got {v!r}")
        setattr(out, key, float(v))
    return out


def record_from_filter(flt: Any, drive: str, software: str | None = None) -> VerificationRecord:
    """What a filter at the end of a drive can vouch for: verified when its set-up hypothesis ran,
    its protection level is within the alert limit and no consistency test is failed (an excluded
    declaration is not a verified one: the set-up that drive found is in the calibration it
    calls for, not in the declaration)."""
    import datetime
    sep = getattr(flt, "separation", None)
    pl = float(sep.protection_m) if sep is not None and sep.active else math.nan
    limit = float(flt.cfg.integrity.alert_limit_m)
    ok = (sep is not None and sep.active and not sep.excluded and math.isfinite(pl) and pl <= limit
          and not flt.consistency.failed)
    return VerificationRecord(verified=bool(ok), drive=str(drive),
                              date=datetime.datetime.now(datetime.timezone.utc).date().isoformat(),
                              protection_m=pl, alert_limit_m=limit, software=software)


def read_verification_file(path: str | Path) -> VerificationRecord | None:
    """The ``[verification]`` record kept in a file of its own (a service's ``[validity]
    verification_file``): None when the file does not exist yet (nothing verified); a file without
    the table, or a malformed one, is a VerificationError naming the file."""
    from v2xpos.compat import tomllib
    p = Path(path)
    if not p.exists():
        return None
    try:
        doc = tomllib.loads(p.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise VerificationError(f"{p}: {exc}") from None
    if "verification" not in doc:
        raise VerificationError(f"{p}: no [verification] table")
    return parse_verification(doc["verification"], f"{p}: [verification]")


def write_verification_file(path: str | Path, record: VerificationRecord) -> None:
    """``record`` as the whole content of ``path`` (written to a temporary file beside it, then
    renamed over it: a reader never sees half a record)."""
    import os
    import tempfile
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=p.parent, prefix=f".{p.name}.", suffix=".tmp")
    with os.fdopen(fd, "w") as fh:
        fh.write(record.to_toml())
    os.replace(tmp, p)


def session_verification(source: Any, path: str | Path, drive: str) -> VerificationRecord | None:
    """At the end of a session: the record of what the source's filter vouches for
    (:func:`record_from_filter`), written to ``path``; None (nothing written) for a source without
    a filter or one whose filter never started. A record that is not verified is written too: the
    next session then starts unverified, as the drive said."""
    flt = getattr(source, "filter", None)
    if flt is None or not getattr(flt, "initialized", False):
        return None
    from v2xpos.provenance import software
    sw = software()
    rev = f" (git {sw['git_revision'][:7]}{', dirty' if sw['git_dirty'] else ''})" if sw["git_revision"] else ""
    record = record_from_filter(flt, drive, f"{sw['name']} {sw['version']}{rev}")
    write_verification_file(path, record)
    return record


def write_session_record(source: Any, path: str | Path, drive: str) -> tuple[dict | None, str]:
    """A service's end of session (``[validity] write_verification``): :func:`session_verification`
    to ``path``, never fatal (the session's data is out whatever happens to its record). Returns the
    summary the service reports (``path``, ``verified``, ``protection_m``; None when nothing was
    written: the file could not be written, or the filter never started) and a line saying which."""
    try:
        record = session_verification(source, path, drive)
    except OSError as exc:
        return None, f"[validity].verification_file {path}: not written: {exc}"
    if record is None:
        return None, f"[validity].verification_file {path}: not written: the filter never started"
    return ({"path": str(path), "verified": record.verified, "protection_m": record.protection_m},
            f"verification record {path}: verified={record.verified} protection {record.protection_m:.3f} m")
