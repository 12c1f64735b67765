"""``load_dataset``: one entry point from a descriptor or a folder to a :class:`v2xpos.types.Dataset`.

Descriptor (``dataset.toml``; paths relative to the toml file)::

    name = "drive_0708"            # required
    platform = "car"               # required: car | pedestrian | quadrotor | ...
    [imu]
    file = "imu_1934.csv"          # required
    format = "csv_g_dps_ms"        # required, see IMU_FORMATS
    timetag = "imu_1934.csv.tag"   # optional RTKLIB TIMETAG of the imu file
    imu_to_body = [[-1,0,0],[0,1,0],[0,0,-1]]   # optional (identity): v_body = M @ v_imu
    [gnss]
    file = "gnss_1934.pos"         # required
    format = "rtklib_pos"          # required, see GNSS_FORMATS
    timetag = "gnss.ubx.tag"       # optional, format "ubx" only: arrival times of its bytes
    lever_arm_m = [0, 0, 0]        # optional: antenna - IMU in body axes [m]
    lever_arm_sd_m = 0.1           # optional [m]
    height_datum = "msl"           # optional (rtklib_pos default "msl", see rtklib_pos)
    raw = "gnss_1730.ubx"          # optional raw u-blox stream
    raw_timetag = "gnss_1730.ubx.tag"

A descriptor for a whole-folder layout instead names it: ``layout = "comma2k19"`` or
``layout = "quadrotor_mimu"`` with ``path = "..."`` (relative to the toml) and optional ``name``
(and, for ``v2xpos grade``, a ``[grade]`` table).

Both may carry a ``[calibration]`` table (``v2xpos.datasets.calibration``). Every table rejects a
key it does not know, naming the file, the table and the key, with a "did you mean" for a near
miss: a misspelt ``imu_to_body`` must not quietly become the identity. An IMU or GNSS file with
fewer than two usable records (empty, header only, all lines malformed) is an error naming it.

A folder is accepted too: one holding ``dataset.toml``, a comma2k19 segment (``processed_log`` +
``global_pose``) or a quadrotor_mimu path folder (``IMU_1.csv`` ... + ``GT.csv``).
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from v2xpos.types import Dataset, GnssData, MultiImuRecording

from v2xpos.compat import tomllib
from v2xpos.schema import check_choice, check_keys

IMU_FORMATS = ("csv_g_dps_ms",)
TOP_KEYS = ("name", "platform", "imu", "gnss", "calibration", "verification")
LAYOUT_KEYS = ("layout", "path", "name", "grade", "calibration", "verification")
IMU_KEYS = ("file", "format", "timetag", "imu_to_body")
GNSS_KEYS = ("file", "format", "timetag", "lever_arm_m", "lever_arm_sd_m", "height_datum", "raw",
             "raw_timetag")
MIN_RECORDS = 2
"""Fewer usable IMU samples or GNSS epochs than this: the file is an error, not a result."""
GNSS_FORMATS = ("rtklib_pos", "ubx")
LAYOUTS = ("comma2k19", "quadrotor_mimu")
log = logging.getLogger(__name__)


def _field(table: dict, key: str, where: str, toml_path: Path, kind: type | tuple = str,
           required: bool = True, default: Any = None) -> Any:
    if key not in table:
        if required:
            raise ValueError(f"{toml_path}: missing field {where}{key}")
        return default
    value = table[key]
    if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool:
        raise ValueError(f"{toml_path}: field {where}{key} has type {type(value).__name__}, "
                         f"expected {getattr(kind, '__name__', kind)}")
    return value


def _all_numbers(value: Any) -> bool:
    if isinstance(value, list):
        return all(_all_numbers(v) for v in value)
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _matrix(value: Any, shape: tuple[int, ...], field_name: str, toml_path: Path) -> np.ndarray:
    if not _all_numbers(value):
        raise ValueError(f"{toml_path}: field {field_name} must hold numbers only, got {value!r}")
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{toml_path}: field {field_name} is not numeric") from None
    if arr.shape != shape or not np.all(np.isfinite(arr)):
        raise ValueError(f"{toml_path}: field {field_name} must be a finite array of shape {shape}, "
                         f"got shape {arr.shape}")
    return arr


def read_descriptor(toml_path: str | Path) -> dict:
    """Parse a descriptor toml; ValueError naming the file on a syntax error."""
    toml_path = Path(toml_path)
    try:
        with open(toml_path, "rb") as fh:
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{toml_path}: not valid TOML: {exc}") from None
    except UnicodeDecodeError as exc:  # added by trust/resilience (fuzz finding): name the file
        raise ValueError(f"{toml_path}: not UTF-8 text: {exc}") from None
    except RecursionError:
        raise ValueError(f"{toml_path}: not valid TOML: nested too deeply") from None


def _load_toml(toml_path: Path, read_raw: bool) -> Dataset:
    from v2xpos.datasets.imu_csv import read_imu_csv
    from v2xpos.datasets.rtklib_pos import read_rtklib_pos

    desc = read_descriptor(toml_path)
    base = toml_path.parent
    if "layout" in desc:
        check_keys(desc, LAYOUT_KEYS, f"{toml_path}: top level (layout descriptor)")
        layout = _field(desc, "layout", "", toml_path)
        check_choice(layout, LAYOUTS, f"{toml_path}: field layout")
        folder = base / _field(desc, "path", "", toml_path)
        if not folder.is_dir():
            raise ValueError(f"{toml_path}: field path: folder {folder} not found")
        ds = _load_layout(layout, folder)
        ds.name = _field(desc, "name", "", toml_path, required=False, default=ds.name)
        ds.source = toml_path
        ds.calibration = _calibration(desc, toml_path)
        ds.verification = _verification(desc, toml_path)
        return ds

    check_keys(desc, TOP_KEYS, f"{toml_path}: top level")
    name = _field(desc, "name", "", toml_path)
    platform = _field(desc, "platform", "", toml_path)
    imu_t = _field(desc, "imu", "", toml_path, kind=dict)
    gnss_t = _field(desc, "gnss", "", toml_path, kind=dict)
    check_keys(imu_t, IMU_KEYS, f"{toml_path}: [imu]")
    check_keys(gnss_t, GNSS_KEYS, f"{toml_path}: [gnss]")
    calibration = _calibration(desc, toml_path)
    verification = _verification(desc, toml_path)

    imu_format = _field(imu_t, "format", "[imu] ", toml_path)
    check_choice(imu_format, IMU_FORMATS, f"{toml_path}: field [imu] format")
    imu_file = base / _field(imu_t, "file", "[imu] ", toml_path)
    timetag = _field(imu_t, "timetag", "[imu] ", toml_path, required=False)
    imu_to_body = _matrix(_field(imu_t, "imu_to_body", "[imu] ", toml_path, kind=list,
                                 required=False, default=np.eye(3).tolist()),
                          (3, 3), "[imu] imu_to_body", toml_path)
    if not np.allclose(imu_to_body @ imu_to_body.T, np.eye(3), atol=1e-6) or np.linalg.det(imu_to_body) < 0:
        raise ValueError(f"{toml_path}: field [imu] imu_to_body is not a rotation matrix "
                         "(orthonormal with determinant +1)")

    gnss_format = _field(gnss_t, "format", "[gnss] ", toml_path)
    check_choice(gnss_format, GNSS_FORMATS, f"{toml_path}: field [gnss] format")
    gnss_file = base / _field(gnss_t, "file", "[gnss] ", toml_path)
    lever = _matrix(_field(gnss_t, "lever_arm_m", "[gnss] ", toml_path, kind=list,
                           required=False, default=[0.0, 0.0, 0.0]),
                    (3,), "[gnss] lever_arm_m", toml_path)
    lever_sd = float(_field(gnss_t, "lever_arm_sd_m", "[gnss] ", toml_path, kind=(int, float),
                            required=False, default=0.1))
    if not (np.isfinite(lever_sd) and lever_sd >= 0.0):
        raise ValueError(f"{toml_path}: field [gnss] lever_arm_sd_m must be a finite number >= 0, "
                         f"got {lever_sd}")
    height_datum = _field(gnss_t, "height_datum", "[gnss] ", toml_path, required=False,
                          default="msl")
    if height_datum not in ("msl", "ellipsoidal"):
        raise ValueError(f"{toml_path}: field [gnss] height_datum must be 'msl' or 'ellipsoidal'")
    raw = _field(gnss_t, "raw", "[gnss] ", toml_path, required=False)
    raw_timetag = _field(gnss_t, "raw_timetag", "[gnss] ", toml_path, required=False)

    gnss_tag = _field(gnss_t, "timetag", "[gnss] ", toml_path, required=False)
    named = [("[imu] file", imu_file), ("[gnss] file", gnss_file)]
    for label, rel in (("[imu] timetag", timetag), ("[gnss] timetag", gnss_tag), ("[gnss] raw", raw),
                       ("[gnss] raw_timetag", raw_timetag)):
        if rel is not None:
            named.append((label, base / rel))
    for label, p in named:
        if not p.is_file():
            raise ValueError(f"{toml_path}: field {label}: file {p} not found")

    imu_res = read_imu_csv(imu_file, base / timetag if timetag else None)
    _enough(len(imu_res.imu), "IMU samples", imu_file, "[imu] file", toml_path, imu_res.issues)
    notes: dict[str, Any] = {"imu": imu_res.summary(), "malformed": [imu_res.issues.as_dict()],
                             "files": {"imu": str(imu_file), "gnss": str(gnss_file),
                                       **({"imu_timetag": str(base / timetag)} if timetag else {})}}
    malformed = imu_res.issues.count
    if imu_res.timetag_issues is not None:
        malformed += imu_res.timetag_issues.count
        notes["malformed"].append(imu_res.timetag_issues.as_dict())
    if timetag is None:
        notes["imu_time"] = "no timetag: t_s is the device counter in seconds, not GPS time"

    if gnss_format == "rtklib_pos":
        gnss, gnss_issues = read_rtklib_pos(gnss_file, height_datum=height_datum)
    else:
        from v2xpos.datasets.ubx import read_ubx
        ubx_res = read_ubx(gnss_file, base / gnss_tag if gnss_tag else None)
        notes["ubx"] = ubx_res.summary()
        gnss, gnss_issues = ubx_res.gnss, ubx_res.issues
    _enough(len(gnss), "GNSS epochs", gnss_file, "[gnss] file", toml_path, gnss_issues)
    malformed += gnss_issues.count
    notes["malformed"].append(gnss_issues.as_dict())
    if timetag is not None:
        covered = np.isfinite(imu_res.arrival_delay_s)
        notes["imu_timetag_coverage"] = float(covered.mean()) if covered.size else 0.0
    notes["gnss"] = {"epochs": len(gnss), "height_datum": gnss.height_datum,
                     "fix_counts": _fix_counts(gnss)}
    if raw is not None:
        notes["gnss_raw"] = str(base / raw)
        if raw_timetag is not None:
            notes["gnss_raw_timetag"] = str(base / raw_timetag)
        if read_raw:
            from v2xpos.datasets.ubx import read_ubx
            ubx_res = read_ubx(base / raw, base / raw_timetag if raw_timetag else None)
            notes["ubx"] = ubx_res.summary()
            notes["ubx_result"] = ubx_res
    for entry in notes["malformed"]:
        if entry["count"]:
            shown = "; ".join(f"line {e['line']}: {e['reason']}" for e in entry["examples"])
            log.warning("%s: %d malformed record(s) skipped (%s)", entry["source"], entry["count"],
                        shown)
    return Dataset(name=name, platform=platform, imu=imu_res.imu, gnss=gnss,
                   imu_to_body=imu_to_body, lever_arm_m=lever, lever_arm_sd_m=lever_sd,
                   malformed_lines=malformed, source=toml_path, notes=notes, calibration=calibration,
                   verification=verification)


def _calibration(desc: dict, toml_path: Path):
    if "calibration" not in desc:
        return None
    from v2xpos.datasets.calibration import parse_calibration
    return parse_calibration(desc["calibration"], f"{toml_path}: [calibration]")


def _verification(desc: dict, toml_path: Path):
    if "verification" not in desc:
        return None
    from v2xpos.datasets.verification import parse_verification
    return parse_verification(desc["verification"], f"{toml_path}: [verification]")


def _enough(n: int, what: str, path: Path, label: str, toml_path: Path, issues) -> None:
    """ValueError naming the data file (and the descriptor field) when it has too few records."""
    if n >= MIN_RECORDS:
        return
    size = path.stat().st_size
    why = ("the file is empty" if size == 0 else
           f"{issues.count} malformed record(s) skipped" if issues.count else
           "no data records (header or comments only)")
    first = f"; first: line {issues.examples[0][0]}: {issues.examples[0][1]}" if issues.examples else ""
    raise ValueError(f"{path}: {n} usable {what}, need at least {MIN_RECORDS}: {why}{first} "
                     f"(named by {toml_path} field {label})")


def _fix_counts(gnss: GnssData) -> dict[str, int]:
    from v2xpos.types import FixStatus
    values, counts = np.unique(np.asarray(gnss.fix, dtype=int), return_counts=True)
    return {FixStatus(int(v)).name: int(c) for v, c in zip(values, counts)}


def _detect_layout(folder: Path) -> str | None:
    if (folder / "processed_log").is_dir() and (folder / "global_pose").is_dir():
        return "comma2k19"
    if (folder / "GT.csv").is_file() and any(folder.glob("IMU_*.csv")):
        return "quadrotor_mimu"
    return None


def _load_layout(layout: str, folder: Path) -> Dataset:
    if layout == "comma2k19":
        from v2xpos.datasets.comma2k19 import load_comma2k19
        return load_comma2k19(folder)
    from v2xpos.datasets.quadrotor import dataset_from_multi_imu, read_quadrotor_path
    return dataset_from_multi_imu(read_quadrotor_path(folder))


def load_dataset(path: str | Path, read_raw: bool = False) -> Dataset:
    """Load a recording from a ``dataset.toml`` descriptor or a dataset folder.

    read_raw: also parse the raw GNSS stream named in the descriptor (UBX; slower) and put its
    summary (message latency) in ``notes["ubx"]``. Raises ValueError naming the file and the
    field for an unknown format, a missing or mistyped field, or an unrecognised folder.
    """
    path = Path(path)
    if path.is_dir():
        if (path / "dataset.toml").is_file():
            return _load_toml(path / "dataset.toml", read_raw)
        layout = _detect_layout(path)
        if layout is None:
            raise ValueError(f"{path}: no dataset.toml and not a known dataset layout {LAYOUTS}")
        return _load_layout(layout, path)
    if not path.is_file():
        raise ValueError(f"{path}: no such dataset file or folder")
    return _load_toml(path, read_raw)


def load_multi_imu(path: str | Path) -> MultiImuRecording:
    """Load a multi-IMU recording (a quadrotor_mimu path folder, or a toml with
    ``layout = "quadrotor_mimu"``) -> :class:`v2xpos.types.MultiImuRecording`."""
    from v2xpos.datasets.quadrotor import read_quadrotor_path
    path = Path(path)
    if path.is_file():
        desc = read_descriptor(path)
        check_keys(desc, LAYOUT_KEYS, f"{path}: top level (layout descriptor)")
        if desc.get("layout") != "quadrotor_mimu":
            raise ValueError(f"{path}: field layout must be 'quadrotor_mimu' for a multi-IMU load")
        folder = path.parent / _field(desc, "path", "", path)
        if not folder.is_dir():
            raise ValueError(f"{path}: field path: folder {folder} not found")
        return read_quadrotor_path(folder)
    if _detect_layout(path) != "quadrotor_mimu":
        raise ValueError(f"{path}: not a multi-IMU folder (need IMU_k.csv and GT.csv)")
    return read_quadrotor_path(path)


def describe(ds: Dataset) -> dict:
    """JSON-ready summary of a loaded dataset: counts, spans [GPS s], rates, clock, malformed."""
    def span(t: np.ndarray) -> list[float] | None:
        return [float(t[0]), float(t[-1])] if len(t) else None

    out: dict[str, Any] = {
        "name": ds.name, "platform": ds.platform, "source": str(ds.source),
        "imu_samples": len(ds.imu), "imu_span_s": span(ds.imu.t_s),
        "gnss_epochs": len(ds.gnss), "gnss_span_s": span(ds.gnss.t_s),
        "gnss_fix_counts": _fix_counts(ds.gnss), "gnss_height_datum": ds.gnss.height_datum,
        "malformed_lines": ds.malformed_lines,
        "imu_to_body": ds.imu_to_body.tolist(), "lever_arm_m": ds.lever_arm_m.tolist(),
    }
    if len(ds.imu) > 1:
        out["imu_rate_hz"] = float((len(ds.imu) - 1) / (ds.imu.t_s[-1] - ds.imu.t_s[0]))
    for key in ("imu", "ubx", "boot_to_gps_clock", "gnss_latency_s", "malformed"):
        if key in ds.notes:
            out[key] = ds.notes[key]
    if ds.wheel is not None:
        out["wheel_samples"] = len(ds.wheel.t_s)
    if ds.reference is not None:
        out["reference_epochs"] = len(ds.reference.t_s)
    return out
