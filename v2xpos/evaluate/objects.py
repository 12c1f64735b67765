"""The sensor's object list: one row per reported object, from a csv or a CAN log.

* csv: header with at least ``t_gps_s,object_id,x_m,y_m,vx_mps,vy_mps`` (sensor frame: x along the
  boresight, y right [m], relative velocity [m/s] in the same frame); optional ``z_m``,
  ``existence``, ``class``; other columns are ignored. ``object_id`` may be any text.
* CAN log: Vector ASC or BLF, or ASAM MDF4 bus logging (``.mf4``; python-can's readers, the MDF4
  one built on asammdf), frames decoded with cantools from the DBC and the signal map of
  SENSOR.toml (``[can]``; every object field from one message, one object per frame). The frame's
  log time is the object's time stamp.

Times: ``clock = "gps"`` takes the stamps as GPS seconds, ``"utc"`` as Unix seconds on UTC
(converted with the leap seconds of ``v2xpos.timebase``). Every time is rounded to 1 us (the
resolution of CAN loggers) and every decoded CAN value to the decimals of its signal's scale, so
that the same log written as csv, ASC, BLF and MDF4 reads back to the same numbers.

Cycles: the objects of one measurement cycle arrive together (one time stamp in a csv, frames a
fraction of a millisecond apart on a bus); consecutive stamps more than ``CYCLE_GAP_S`` apart start
a new cycle. The cycle period is the median spacing of cycle starts; cycles with no object at all
leave no row and are re-inserted on that grid (``cycle_grid``).
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .config import OBJECT_FIELDS, SensorConfig

CSV_COLUMNS = ("t_gps_s", "object_id", "x_m", "y_m", "vx_mps", "vy_mps")
CAN_SUFFIXES = {".asc": "asc", ".blf": "blf", ".mf4": "mf4", ".mdf": "mf4"}
CYCLE_GAP_S = 0.005
"""Stamps further apart than this belong to different cycles: well above the spacing of one cycle's
frames on a CAN bus (a 8-byte frame takes 0.13-0.26 ms at 1-0.5 Mbit/s) and well below the period
of any object-list sensor (>= 10 ms)."""


class ObjectListError(ValueError):
    """An object list that cannot be used (the message names the file and what is wrong)."""


@dataclass
class ObjectList:
    """Rows sorted by time: t_s (N,) GPS s, object_id (N,) str, x_m, y_m, vx_mps, vy_mps, z_m (N,)
    (z NaN when not given), existence (N,) (NaN when not given), cls (N,) str; cycle (N,) int."""
    path: Path
    fmt: str
    t_s: np.ndarray
    object_id: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    vx_mps: np.ndarray
    vy_mps: np.ndarray
    z_m: np.ndarray
    existence: np.ndarray
    cls: np.ndarray
    skipped: int = 0
    cycle: np.ndarray | None = None
    cycle_t_s: np.ndarray | None = None
    id_code: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.t_s)

    def subset(self, rows: np.ndarray) -> "ObjectList":
        """The rows ``rows`` (their cycle indices and id codes kept, cycle_t_s shared)."""
        take = {name: getattr(self, name)[rows] for name in ROW_FIELDS + ("cycle", "id_code")}
        return ObjectList(path=self.path, fmt=self.fmt, skipped=self.skipped, cycle_t_s=self.cycle_t_s, **take)


ROW_FIELDS = ("t_s", "object_id", "x_m", "y_m", "vx_mps", "vy_mps", "z_m", "existence", "cls")


def _finish(path: Path, fmt: str, cols: dict, skipped: int) -> ObjectList:
    n = len(cols["t_s"])
    if n == 0:
        raise ObjectListError(f"{path}: no object rows")
    order = np.argsort(cols["t_s"], kind="stable")

    def arr(key, fill, dtype=float):
        v = cols.get(key)
        return np.full(n, fill, dtype=dtype)[order] if v is None else np.asarray(v, dtype=dtype)[order]

    objs = ObjectList(path=path, fmt=fmt, t_s=np.round(np.asarray(cols["t_s"], float)[order], 6),
                      object_id=np.asarray(cols["object_id"]).astype(str)[order],
                      x_m=arr("x_m", np.nan), y_m=arr("y_m", np.nan), vx_mps=arr("vx_mps", np.nan),
                      vy_mps=arr("vy_mps", np.nan), z_m=arr("z_m", np.nan), existence=arr("existence", np.nan),
                      cls=arr("class", "", dtype=object).astype(str), skipped=skipped)
    bad = ~(np.isfinite(objs.t_s) & np.isfinite(objs.x_m) & np.isfinite(objs.y_m))
    if bad.all():
        raise ObjectListError(f"{path}: no row with a finite time and position")
    if bad.any():
        keep = ~bad
        for name in ROW_FIELDS:
            setattr(objs, name, getattr(objs, name)[keep])
        objs.skipped += int(bad.sum())
    objs.cycle, objs.cycle_t_s = split_cycles(objs.t_s)
    objs.id_code = np.unique(objs.object_id, return_inverse=True)[1].reshape(-1)
    return objs


def split_cycles(t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cycle index of each sorted stamp and each cycle's first stamp (``CYCLE_GAP_S``)."""
    new = np.concatenate([[True], np.diff(t_s) > CYCLE_GAP_S])
    cycle = np.cumsum(new) - 1
    return cycle, t_s[new]


def cycle_grid(cycle_t_s: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Every cycle time including the empty cycles (no rows): the observed cycle starts, and in a
    gap longer than 1.5 periods round(gap / period) - 1 evenly spaced cycles. Returns (times,
    period, index of each observed cycle in times)."""
    n = len(cycle_t_s)
    if n < 2:
        return cycle_t_s.copy(), math.nan, np.arange(n)
    d = np.diff(cycle_t_s)
    period = float(np.median(d))
    n_missing = np.where(d > 1.5 * period, np.round(d / period) - 1, 0).astype(int)
    observed = np.arange(n) + np.concatenate([[0], np.cumsum(n_missing)])
    grid = np.empty(n + int(n_missing.sum()))
    grid[observed] = cycle_t_s
    for k in np.flatnonzero(n_missing):
        m = n_missing[k]
        grid[observed[k] + 1:observed[k] + 1 + m] = cycle_t_s[k] + d[k] * np.arange(1, m + 1) / (m + 1)
    return grid, period, observed


def read_csv_objects(path: Path) -> ObjectList:
    """csv object list: numpy's C reader for a plain file (numbers, ids without quotes or empty
    fields), else the csv module (quotes, empty fields, short rows)."""
    with open(path, newline="") as f:
        header = [h.strip() for h in f.readline().split(",")]
    if all(c in header for c in CSV_COLUMNS):
        wanted = [c for c in (*CSV_COLUMNS, "z_m", "existence") if c in header]
        try:
            num = np.loadtxt(path, delimiter=",", skiprows=1, usecols=[header.index(c) for c in wanted if c != "object_id"],
                             dtype=float, ndmin=2, comments=None)
            ids = np.loadtxt(path, delimiter=",", skiprows=1, usecols=header.index("object_id"), dtype=str,
                             ndmin=1, comments=None)
            cls = (np.loadtxt(path, delimiter=",", skiprows=1, usecols=header.index("class"), dtype=str, ndmin=1,
                              comments=None) if "class" in header else None)
        except ValueError:
            return _read_csv_objects_slow(path)
        names = [c for c in wanted if c != "object_id"]
        cols = {("t_s" if c == "t_gps_s" else c): num[:, j] for j, c in enumerate(names)}
        cols["object_id"] = np.char.strip(ids)
        if cls is not None:
            cols["class"] = cls
        return _finish(path, "csv", cols, 0)
    return _read_csv_objects_slow(path)


def read_csv_table(path: Path, required: tuple[str, ...], error: type[ValueError]) -> tuple[list[str], list[list[str]]]:
    """Header and non-empty rows of a csv file; ``error`` naming the file and the missing columns
    (with a "did you mean" for a misspelt one) when a required column is not in the header."""
    with open(path, newline="") as f:
        reader = csv.reader(f)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise error(f"{path}: empty file") from None
        missing = [c for c in required if c not in header]
        if missing:
            from v2xpos.schema import did_you_mean
            hint = "".join(did_you_mean(m, header).replace(" (did you mean", f" ({m!r}: did you mean") for m in missing)
            raise error(f"{path}: missing column(s) {missing}{hint}; header {header}")
        return header, [r for r in reader if r and any(x.strip() for x in r)]


def _read_csv_objects_slow(path: Path) -> ObjectList:
    header, rows = read_csv_table(path, CSV_COLUMNS, ObjectListError)
    idx = {name: header.index(name) for name in (*CSV_COLUMNS, "z_m", "existence", "class") if name in header}
    width = max(idx.values()) + 1
    short = sum(1 for r in rows if len(r) < width)
    rows = [r for r in rows if len(r) >= width]
    cols: dict = {}
    for name, j in idx.items():
        col = [r[j].strip() for r in rows]
        if name in ("object_id", "class"):
            cols[name] = col
            continue
        values = np.array([x if x else "nan" for x in col])
        try:
            cols["t_s" if name == "t_gps_s" else name] = values.astype(float)
        except ValueError:
            bad = next(k for k, x in enumerate(col) if x and not _is_number(x))
            raise ObjectListError(f"{path}: row {bad + 2} column {name}: not a number: {col[bad]!r}") from None
    return _finish(path, "csv", cols, short)


def _is_number(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def _decimals(scale: float) -> int | None:
    """Decimals of a signal's scale (0.01 -> 2), None when it is not a power of ten's fraction."""
    if scale <= 0:
        return None
    d = -math.log10(scale)
    k = int(round(d))
    return max(k, 0) if abs(d - k) < 1e-9 else None


def read_can_objects(path: Path, cfg: SensorConfig) -> ObjectList:
    """Objects from a CAN log (module docstring); frames of other messages are ignored."""
    import can
    import cantools
    fmt = CAN_SUFFIXES[path.suffix.lower()]
    if cfg.can is None:
        raise ObjectListError(f"{path}: a CAN log needs a [can] table (dbc, signals) in {cfg.path}")
    try:
        db = cantools.database.load_file(str(cfg.can.dbc))
    except FileNotFoundError:
        raise ObjectListError(f"{cfg.path}: [can].dbc: file not found: {cfg.can.dbc}") from None
    except Exception as exc:  # noqa: BLE001 -- cantools raises its own parse errors
        raise ObjectListError(f"{cfg.can.dbc}: not a readable DBC: {exc}") from None
    refs = cfg.can.signals
    msg_name = next(iter(refs.values())).message
    try:
        message = db.get_message_by_name(msg_name)
    except KeyError:
        raise ObjectListError(f"{cfg.path}: [can.signals]: message {msg_name!r} is not in {cfg.can.dbc} "
                              f"(messages: {sorted(m.name for m in db.messages)[:20]})") from None
    names = {s.name: s for s in message.signals}
    for field_name, ref in refs.items():
        if ref.signal not in names:
            from v2xpos.schema import did_you_mean
            raise ObjectListError(f"{cfg.path}: [can.signals].{field_name}: signal {ref.signal!r} is not in message "
                                  f"{msg_name!r} of {cfg.can.dbc}{did_you_mean(ref.signal, names)}")
    decimals = {f: _decimals(abs(names[r.signal].scale * r.scale)) for f, r in refs.items()}
    cols: dict[str, list] = {"t_s": [], **{f: [] for f in refs}}
    skipped = 0
    try:
        reader = can.LogReader(str(path), **({"relative_timestamp": False} if fmt == "asc" else {}))
        frames = iter(reader)
        for frame in frames:
            if frame.is_error_frame or frame.is_remote_frame or frame.arbitration_id != message.frame_id:
                continue
            try:
                decoded = message.decode(bytes(frame.data), decode_choices=False, scaling=True)
            except Exception:  # noqa: BLE001 -- a short or corrupt frame: counted, not fatal
                skipped += 1
                continue
            cols["t_s"].append(frame.timestamp)
            for f, r in refs.items():
                v = r.scale * float(decoded[r.signal]) + r.offset
                cols[f].append(v)
    except (OSError, ValueError, EOFError) as exc:
        raise ObjectListError(f"{path}: cannot read the {fmt.upper()} log: {exc}") from None
    except Exception as exc:  # noqa: BLE001 -- the readers raise their own format errors
        raise ObjectListError(f"{path}: cannot read the {fmt.upper()} log: {type(exc).__name__}: {exc}") from None
    if not cols["t_s"]:
        raise ObjectListError(f"{path}: no frame of message {msg_name!r} (id 0x{message.frame_id:x}) from "
                              f"{cfg.can.dbc}")
    for f, k in decimals.items():
        if k is not None:
            cols[f] = np.round(np.asarray(cols[f], float), k)
    cols["object_id"] = [str(int(v)) if float(v).is_integer() else repr(v) for v in cols.pop("object_id")]
    return _finish(path, fmt, cols, skipped)


def read_objects(path: str | Path, cfg: SensorConfig) -> ObjectList:
    """The object list at ``path`` (csv or a CAN log by its suffix), times converted to GPS seconds."""
    path = Path(path)
    if not path.is_file():
        raise ObjectListError(f"{path}: file not found")
    suffix = path.suffix.lower()
    if suffix in CAN_SUFFIXES:
        objs = read_can_objects(path, cfg)
    elif suffix in (".csv", ".txt"):
        objs = read_csv_objects(path)
    else:
        raise ObjectListError(f"{path}: unknown object list format {suffix!r}: .csv, or a CAN log "
                              f"({', '.join(sorted(CAN_SUFFIXES))}) with a [can] table in {cfg.path}")
    if cfg.clock == "utc":
        from v2xpos.timebase import unix_to_gps_seconds
        objs.t_s = np.round(np.asarray(unix_to_gps_seconds(objs.t_s), float), 6)
        objs.cycle, objs.cycle_t_s = split_cycles(objs.t_s)
    return objs


__all__ = ["ObjectList", "ObjectListError", "read_objects", "cycle_grid", "split_cycles", "CSV_COLUMNS",
           "OBJECT_FIELDS"]
