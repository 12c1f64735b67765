"""The damages of the bad-input corpus (``bench.corpus``): each generator turns one valid input -- a
dataset descriptor, an IMU csv, a ``.pos``, a TIMETAG, a multi-IMU folder, a service config --
into (name, damaged content) pairs, each a deliberate damage that must be noticed (a mutation that
leaves the input valid with the same meaning is not generated)."""
from __future__ import annotations

import random
import re
import struct
from pathlib import Path

import tomli_w


# ------------------------------------------------------------------------------------ misspellings
def misspellings(key: str, rng: random.Random, n: int = 4) -> list[str]:
    """Near misses a person types: a letter dropped, two swapped, one doubled, ``_`` -> ``-``, a
    plural, ``_to_`` -> ``_2_``, a unit suffix doubled (``_m`` -> ``_mm``)."""
    out = set()
    if len(key) > 2:
        i = rng.randrange(1, len(key) - 1)
        out.add(key[:i] + key[i + 1:])
        out.add(key[:i] + key[i + 1] + key[i] + key[i + 2:] if i + 1 < len(key) else key + "x")
        out.add(key[:i] + key[i] + key[i:])
    out.add(key.replace("_", "-") if "_" in key else key + "s")
    out.add(key + "s")
    if "_to_" in key:
        out.add(key.replace("_to_", "_2_"))
    if key.endswith("_m"):
        out.add(key + "m")
    out.discard(key)
    words = sorted(out)
    rng.shuffle(words)
    return words[:n]



# ------------------------------------------------------------------------------------ generators
def _sub_line(text: str, pattern: str, repl: str) -> str:
    new, n = re.subn(pattern, repl, text, count=1, flags=re.M)
    if n != 1:
        raise ValueError(f"pattern {pattern!r} not found")
    return new


def dataset_toml_damages(desc: str, rng: random.Random) -> list[tuple[str, str | bytes]]:
    """(name, damaged descriptor) pairs: misspelt / missing / mistyped / misplaced keys, wrong
    matrices and vectors, unknown formats, missing files, broken TOML, a bad [calibration]."""
    out: list[tuple[str, str | bytes]] = []
    keys = {"": ["name", "platform"], "imu": ["file", "format", "timetag", "imu_to_body"],
            "gnss": ["file", "format", "lever_arm_m", "lever_arm_sd_m"]}
    for table, names in keys.items():
        for key in names:
            for bad in misspellings(key, rng, 5):
                out.append((f"misspelt {table or 'top'}.{key} -> {bad}",
                            _sub_line(desc, rf"^{key}(\s*=)", bad + r"\1") if not table else
                            _retable(desc, table, key, bad)))
    for table, names in keys.items():
        for key in names:
            line = re.search(rf"^{key}\s*=.*$", desc[slice(*_table_span(desc, table))], flags=re.M).group(0)
            out.append((f"TOML: {table or 'top'}.{key} given twice", _set(desc, table, key, line.split("=", 1)[1].strip())
                        .replace(line, line + "\n" + line, 1)))
    for table, key in (("", "name"), ("", "platform"), ("imu", "file"), ("imu", "format"), ("imu", "timetag"),
                       ("imu", "imu_to_body"), ("gnss", "file"), ("gnss", "format")):
        out.append((f"missing {table or 'top'}.{key}", _drop(desc, table, key)))
    wrong_types = {"name": ["3", "[1, 2]", "true"], "platform": ["1.5", "{ a = 1 }"],
                   "file": ["7", "[\"imu.csv\"]"], "format": ["1", "false"], "timetag": ["0", "[1]"],
                   "imu_to_body": ['"identity"', "1", "true"], "lever_arm_m": ['"0,0,0"', "0.5", "{ x = 1 }"],
                   "lever_arm_sd_m": ['"0.1"', "[0.1]", "true"]}
    for table, names in keys.items():
        for key in names:
            for v in wrong_types[key]:
                out.append((f"mistyped {table or 'top'}.{key} = {v}", _set(desc, table, key, v)))
    for label, m in (("2x3", "[[1, 0, 0], [0, 1, 0]]"), ("3x2", "[[1, 0], [0, 1], [0, 0]]"),
                     ("flat", "[-1, 0, 0, 0, 1, 0, 0, 0, -1]"), ("string element", '[[-1, 0, 0], [0, "1", 0], [0, 0, -1]]'),
                     ("scaled", "[[-2, 0, 0], [0, 2, 0], [0, 0, -2]]"), ("mirror", "[[1, 0, 0], [0, 1, 0], [0, 0, -1]]"),
                     ("nan", "[[-1, 0, 0], [0, 1, 0], [0, 0, nan]]"), ("inf", "[[-1, 0, 0], [0, inf, 0], [0, 0, -1]]"),
                     ("identity (z up read as down)", "[[1, 0, 0], [0, 1, 0], [0, 0, 1]]"),
                     ("180 deg about x", "[[-1, 0, 0], [0, -1, 0], [0, 0, 1]]"),
                     ("90 deg about x", "[[-1, 0, 0], [0, 0, -1], [0, -1, 0]]"),
                     ("90 deg about y", "[[0, 0, 1], [0, 1, 0], [-1, 0, 0]]"),
                     ("sheared", "[[-1, 0.3, 0], [0, 1, 0], [0, 0, -1]]"), ("empty", "[]")):
        out.append((f"wrong imu_to_body: {label}", _set(desc, "imu", "imu_to_body", m)))
    for label, v in (("2 elements", "[0.0, 0.0]"), ("4 elements", "[0, 0, 0, 0]"), ("nan", "[0, nan, 0]"),
                     ("inf", "[inf, 0, 0]"), ("nested", "[[0, 0, 0]]")):
        out.append((f"wrong lever_arm_m: {label}", _set(desc, "gnss", "lever_arm_m", v)))
    for v in ("-0.1", "nan", "inf"):
        out.append((f"wrong lever_arm_sd_m = {v}", _set(desc, "gnss", "lever_arm_sd_m", v)))
    for table, v in (("imu", '"csv_ms2_rads_ms"'), ("imu", '"CSV_G_DPS_MS"'), ("gnss", '"nmea"'), ("gnss", '"rtklib"')):
        out.append((f"unknown {table}.format {v}", _set(desc, table, "format", v)))
    out.append(("unknown height_datum", desc.replace("[gnss]\n", '[gnss]\nheight_datum = "wgs84"\n')))
    for table, key, v in (("imu", "file", '"no_such.csv"'), ("gnss", "file", '"no_such.pos"'),
                          ("imu", "timetag", '"no_such.tag"'), ("imu", "file", '"."'), ("gnss", "file", '""')):
        out.append((f"missing file {table}.{key} = {v}", _set(desc, table, key, v)))
    out.append(("raw stream declared but missing", desc.replace("[gnss]\n", '[gnss]\nraw = "gnss.ubx"\n')))
    out.append(("imu_to_body under [gnss]", _move(desc, "imu", "gnss", "imu_to_body")))
    out.append(("lever_arm_m under [imu]", _move(desc, "gnss", "imu", "lever_arm_m")))
    out.append(("lever_arm_m at top level", _move(desc, "gnss", "", "lever_arm_m")))
    out.append(("unknown table [imu2]", desc + '\n[imu2]\nfile = "imu_1934.csv"\n'))
    out.append(("unknown table [gnss.options]", desc + "\n[gnss.options]\nelevation_mask_deg = 15\n"))
    out.append(("unknown top-level key", 'version = 2\n' + desc))
    cal_bad = ('[calibration]\nimu_time_offset = { value = 0.01, sd = 0.001 }\n',
               '[calibration]\ngnss_lever_arm_m = { value = [0.1, 0.2], sd = [0.01, 0.01, 0.01] }\n',
               '[calibration]\nimu_time_offset_s = { value = 0.01, sd = -0.001 }\n',
               '[calibration]\nimu_time_offset_s = { value = 0.01 }\n',
               '[calibration]\nimu_time_offset_s = 0.01\n',
               '[calibration]\ngyro_scale = { value = [0, 0, "x"], sd = [0, 0, 0] }\n',
               '[calibration]\nimu_time_offset_s = { value = 0.01, sd = 0.001, unit = "s" }\n')
    for i, c in enumerate(cal_bad):
        out.append((f"bad [calibration] {i}", desc + "\n" + c))
    out.append(("TOML: unterminated string", desc.replace('name = "drive_0708"', 'name = "drive_0708')))
    out.append(("TOML: table header not closed", desc.replace("[gnss]", "[gnss")))
    out.append(("TOML: duplicate key", desc.replace("[imu]\n", '[imu]\nformat = "csv_g_dps_ms"\n')))
    out.append(("TOML: duplicate table", desc + "\n[imu]\n"))
    out.append(("TOML: value without key", desc.replace("[imu]\n", "[imu]\n= 3\n")))
    out.append(("TOML: garbage line", desc.replace("[gnss]\n", "[gnss]\nthis is not toml\n")))
    out.append(("TOML: matrix bracket missing", desc.replace("[0.0, 0.0, -1.0]]", "[0.0, 0.0, -1.0]")))
    out.append(("TOML: non-UTF-8 byte", desc.encode().replace(b"drive_0708", b"drive\xff0708", 1)))
    out.append(("TOML: UTF-16", desc.encode("utf-16")))
    out.append(("TOML: empty", ""))
    out.append(("TOML: cut in the middle of a string", desc[:desc.index('format = "csv') + 12]))
    return out


def _table_span(desc: str, table: str) -> tuple[int, int]:
    if not table:
        m = re.search(r"^\[", desc, flags=re.M)
        return 0, m.start() if m else len(desc)
    m = re.search(rf"^\[{table}\]\s*$", desc, flags=re.M)
    if m is None:
        raise ValueError(table)
    n = re.search(r"^\[", desc[m.end():], flags=re.M)
    return m.end(), m.end() + n.start() if n else len(desc)


def _retable(desc: str, table: str, key: str, new_key: str) -> str:
    a, b = _table_span(desc, table)
    return desc[:a] + _sub_line(desc[a:b], rf"^{key}(\s*=)", new_key + r"\1") + desc[b:]


def _drop(desc: str, table: str, key: str) -> str:
    a, b = _table_span(desc, table)
    return desc[:a] + _sub_line(desc[a:b], rf"^{key}\s*=.*\n", "") + desc[b:]


def _set(desc: str, table: str, key: str, value: str) -> str:
    a, b = _table_span(desc, table)
    part = desc[a:b]
    if re.search(rf"^{key}\s*=", part, flags=re.M):
        part = _sub_line(part, rf"^{key}\s*=.*$", f"{key} = {value}")
    else:
        part = f"\n{key} = {value}\n" + part
    return desc[:a] + part + desc[b:]


def _move(desc: str, src: str, dst: str, key: str) -> str:
    a, b = _table_span(desc, src)
    line = re.search(rf"^{key}\s*=.*\n", desc[a:b], flags=re.M).group(0)
    d = _drop(desc, src, key)
    if not dst:
        return line + d
    a, _ = _table_span(d, dst)
    return d[:a] + "\n" + line + d[a:]


def csv_damages(csv: bytes, rng: random.Random) -> list[tuple[str, bytes]]:
    """(name, damaged IMU csv) pairs."""
    lines = csv.split(b"\n")
    out: list[tuple[str, bytes]] = []
    for share in (0.02, 0.05, 0.1, 0.2, 0.35, 0.5, 0.65, 0.8, 0.9):
        cut = int(len(csv) * share) + rng.randrange(3, 30)
        out.append((f"csv truncated at {share:.0%} (mid-line)", csv[:cut]))
    half = b"\n".join(lines[:len(lines) // 2]) + b"\n"
    out.append(("csv cut in half at a line end", half))
    out.append(("csv second half only", b"\n".join(lines[len(lines) // 2:])))
    out.append(("csv empty", b""))
    out.append(("csv header only", b"ax,ay,az,gx,gy,gz,counter\r\n"))
    out.append(("csv header + 1 line", b"ax,ay,az,gx,gy,gz,counter\r\n" + lines[0] + b"\n"))
    for n in (1, 5, 50):
        ls = list(lines)
        for _ in range(n):
            ls.insert(rng.randrange(1, len(ls) - 1), rng.choice([b"garbage here\r", b"1,2,3\r", b"nan,nan,nan,nan,nan,nan,nan\r",
                                                                 b"\x00\x01\x02\xff\r", b",,,,,,\r"]))
        out.append((f"csv {n} garbage line(s)", b"\n".join(ls)))
    for n in (1, 20):
        b = bytearray(csv)
        for _ in range(n):
            i = rng.randrange(len(b))
            b[i] = rng.choice([0xff, 0xe9, 0xc3, 0x80])
        out.append((f"csv {n} non-UTF-8 byte(s)", bytes(b)))
    a, b = int(len(lines) * 0.4), int(len(lines) * 0.6)
    out.append(("csv 20 % removed in the middle (gap)", b"\n".join(lines[:a] + lines[b:])))
    out.append(("csv a block moved earlier (counter out of order)",
                b"\n".join(lines[:a] + lines[b:b + 200] + lines[a:b] + lines[b + 200:])))
    out.append(("csv last column dropped", b"\n".join(ln.rsplit(b",", 1)[0] + (b"\r" if ln.endswith(b"\r") else b"")
                                                   if ln.strip() else ln for ln in lines)))
    out.append(("csv semicolon separated", csv.replace(b",", b";")))
    out.append(("csv accelerometer in m/s^2 instead of g", _scale_columns(lines, (0, 1, 2), 9.80665)))
    out.append(("csv accel and gyro columns swapped", _swap_columns(lines)))
    out.append(("csv binary junk", bytes(rng.randrange(256) for _ in range(4000))))
    return out


def _scale_columns(lines: list[bytes], cols: tuple[int, ...], factor: float) -> bytes:
    out = []
    for ln in lines:
        f = ln.rstrip(b"\r").split(b",")
        if len(f) == 7:
            try:
                for c in cols:
                    f[c] = f"{float(f[c]) * factor:.3f}".encode()
            except ValueError:
                pass
            ln = b",".join(f) + b"\r"
        out.append(ln)
    return b"\n".join(out)


def _swap_columns(lines: list[bytes]) -> bytes:
    out = []
    for ln in lines:
        f = ln.rstrip(b"\r").split(b",")
        if len(f) == 7:
            ln = b",".join(f[3:6] + f[0:3] + f[6:]) + b"\r"
        out.append(ln)
    return b"\n".join(out)


def pos_damages(pos: str, rng: random.Random) -> list[tuple[str, bytes]]:
    """(name, damaged .pos) pairs."""
    lines = pos.splitlines(keepends=True)
    head = [ln for ln in lines if ln.startswith("%")]
    data = [ln for ln in lines if not ln.startswith("%")]
    enc = (lambda ls: "".join(ls).encode())
    out: list[tuple[str, bytes]] = [("pos headers only", enc(head)), ("pos empty", b""),
                                    ("pos one epoch", enc(head + data[:1]))]
    for share in (0.03, 0.1, 0.3, 0.5, 0.7, 0.9):
        text = enc(lines)
        out.append((f"pos truncated at {share:.0%}", text[:int(len(text) * share) + rng.randrange(3, 40)]))
    cols = head[-1]
    out.append(("pos column header renamed (latitude)", enc(head[:-1] + [cols.replace("latitude(deg)", "lat(deg)")] + data)))
    out.append(("pos required column sdn removed", enc(head[:-1] + [cols.replace(" sdn(m)", "")] +
                                                      [_drop_field(ln, 7) for ln in data])))
    out.append(("pos header announces an extra column", enc(head[:-1] + [cols.rstrip("\n") + " extra\n"] + data)))
    out.append(("pos ECEF header", enc(head[:-1] + [cols.replace("latitude(deg)", "x-ecef(m)")
                                                    .replace("longitude(deg)", "y-ecef(m)").replace("height(m)", "z-ecef(m)")] + data)))
    out.append(("pos JST time system", enc(head[:-1] + [cols.replace("GPST", "JST")] + data)))
    for n in (1, 10):
        ls = list(data)
        for _ in range(n):
            ls.insert(rng.randrange(len(ls)), rng.choice(["garbage\n", "2025/07/08 19:00:00.000 1 2\n", "\x00\x00\n"]))
        out.append((f"pos {n} garbage line(s)", enc(head + ls)))
    b = bytearray(enc(lines))
    for _ in range(10):
        i = rng.randrange(len(enc(head)), len(b))
        b[i] = 0xff
    out.append(("pos non-UTF-8 bytes", bytes(b)))
    ls = list(data)
    i = len(ls) // 2
    ls[i], ls[i + 5] = ls[i + 5], ls[i]
    out.append(("pos epochs out of order", enc(head + ls)))
    out.append(("pos latitude out of range", enc(head + [re.sub(r"^(\S+ \S+\s+)\S+", r"\g<1>123.000000000", ln)
                                                       if k % 7 == 0 else ln for k, ln in enumerate(data)])))
    out.append(("pos every second field missing", enc(head + [" ".join(ln.split()[::2]) + "\n" for ln in data])))
    out.append(("pos dropped 30 % in the middle", enc(head + data[:int(len(data) * 0.35)] + data[int(len(data) * 0.65):])))
    return out


def _drop_field(line: str, k: int) -> str:
    f = line.split()
    return " ".join(f[:k] + f[k + 1:]) + "\n" if len(f) > k else line


def tag_damages(tag: bytes, rng: random.Random) -> list[tuple[str, bytes]]:
    """(name, damaged TIMETAG) pairs."""
    from v2xpos.datasets.timetag import HEADER_BYTES, HEADER_TEXT_BYTES
    out = [("tag empty", b""), ("tag truncated in the header", tag[:30]),
           ("tag header only", tag[:HEADER_BYTES]),
           ("tag wrong header text", b"TIMETAB" + tag[7:]), ("tag header of another tool", b"RINEX   " + tag[8:]),
           ("tag 3 records", tag[:HEADER_BYTES + 3 * 8]),
           ("tag truncated at 50 % (partial record)", tag[:HEADER_BYTES + ((len(tag) - HEADER_BYTES) // 2) + 3]),
           ("tag truncated at 80 %", tag[:HEADER_BYTES + int((len(tag) - HEADER_BYTES) * 0.8) // 8 * 8])]
    b = bytearray(tag)
    b[HEADER_TEXT_BYTES + 4:HEADER_TEXT_BYTES + 8] = struct.pack("<I", 0)
    out.append(("tag file-open time zeroed (1970)", bytes(b)))
    b = bytearray(tag)
    b[HEADER_TEXT_BYTES + 4:HEADER_TEXT_BYTES + 8] = struct.pack("<I", struct.unpack("<I", tag[64:68])[0] + 86400 * 30)
    out.append(("tag file-open time a month late", bytes(b)))
    recs = tag[HEADER_BYTES:]
    n = len(recs) // 8
    half = n // 2
    out.append(("tag records in reverse order", tag[:HEADER_BYTES] + b"".join(recs[8 * i:8 * i + 8] for i in range(n - 1, -1, -1))))
    out.append(("tag second half moved first", tag[:HEADER_BYTES] + recs[8 * half:8 * n] + recs[:8 * half]))
    b = bytearray(tag)
    for k in range(half, half + 5):
        b[HEADER_BYTES + 8 * k + 3] = 0xff   # ms since open jumps by ~4.7 hours
    out.append(("tag 5 records with a corrupt time", bytes(b)))
    out.append(("tag is the csv", b"0.001,0.002,1.000,0.1,0.2,0.3,1000\r\n" * 20))
    return out


def grade_damages(folder: Path, rng: random.Random) -> list[tuple[str, str, bytes | str]]:
    """(name, file name in the folder or 'grade.toml', damaged content) for a quadrotor path."""
    out: list[tuple[str, str, bytes | str]] = []
    imu = (folder / "IMU_2.csv").read_bytes()
    gt = (folder / "GT.csv").read_bytes()
    for share in (0.05, 0.15, 0.33, 0.6, 0.9):
        out.append((f"grade IMU_2 truncated at {share:.0%}", "IMU_2.csv", imu[:int(len(imu) * share) + rng.randrange(3, 30)]))
    head = imu.split(b"\n", 1)[0] + b"\n"
    out += [("grade IMU_2 empty", "IMU_2.csv", b""), ("grade IMU_2 header only", "IMU_2.csv", head),
            ("grade IMU_2 header renamed", "IMU_2.csv", imu.replace(b"Gyr_X", b"GyrX", 1)),
            ("grade IMU_2 garbage lines", "IMU_2.csv", imu.replace(b"\n", b"\ngarbage,1,2\n", 3)),
            ("grade IMU_2 non-UTF-8", "IMU_2.csv", imu[:5000] + b"\xff\xfe" + imu[5000:]),
            ("grade IMU_2 second half only", "IMU_2.csv", head + imu[len(imu) // 2:].split(b"\n", 1)[1]),
            ("grade GT empty", "GT.csv", b""), ("grade GT header only", "GT.csv", gt.split(b"\n", 1)[0] + b"\n"),
            ("grade GT truncated at 30 %", "GT.csv", gt[:int(len(gt) * 0.3)]),
            ("grade GT column missing", "GT.csv", gt.replace(b"North", b"Nord", 1))]
    base_toml = 'layout = "quadrotor_mimu"\npath = "."\n'
    for key in ("reference", "window_s", "step_s", "mounting_xyz_deg"):
        for bad in misspellings(key, rng, 3):
            out.append((f"grade [grade] {key} misspelt {bad}", "grade.toml", base_toml + f"[grade]\n{bad} = 1\n"))
    for label, body in (("window_s string", 'window_s = "1"'), ("step_s negative", "step_s = -0.5"),
                        ("window_s zero", "window_s = 0"), ("reference unknown", 'reference = "IMU_9"'),
                        ("reference number", "reference = 2"), ("mounting scalar", "mounting_xyz_deg = 3"),
                        ("mounting unknown unit", "[grade.mounting_xyz_deg]\nIMU_7 = [0, 0, 0]"),
                        ("mounting 2 angles", "[grade.mounting_xyz_deg]\nIMU_1 = [0, 0]"),
                        ("mounting string angle", '[grade.mounting_xyz_deg]\nIMU_1 = [0, "x", 0]')):
        out.append((f"grade [grade] {label}", "grade.toml", base_toml + "[grade]\n" + body + "\n"))
    out.append(("grade toml unknown top-level key", "grade.toml", base_toml + "units = 4\n"))
    out.append(("grade toml layout misspelt", "grade.toml", base_toml.replace("layout", "layuot")))
    out.append(("grade toml path to nowhere", "grade.toml", base_toml.replace('"."', '"nowhere"')))
    return out


def config_damages(text: str, rng: random.Random, scenario_params: bool = True) -> list[tuple[str, bytes]]:
    """(name, damaged config) pairs from a service config: every key misspelt and mistyped, unknown
    tables, broken TOML, scenario parameters misspelt or mistyped."""
    from v2xpos.compat import tomllib
    d = tomllib.loads(text)
    out: list[tuple[str, bytes]] = []

    def paths(t: dict, prefix: tuple = ()) -> list[tuple]:
        res = []
        for k, v in t.items():
            res.append(prefix + (k,))
            if isinstance(v, dict):
                res += paths(v, prefix + (k,))
        return res

    def edit(path: tuple, fn) -> dict:
        import copy
        c = copy.deepcopy(d)
        t = c
        for k in path[:-1]:
            t = t[k]
        fn(t, path[-1])
        return c

    for p in paths(d):
        if len(p) >= 2 and p[-2] in FREE_KEY_TABLES:
            if p[-2] == "params":
                continue   # scenario parameters: below
            v = _get(d, p)   # the keys are the user's names (target ids): only the values can be wrong
            for wrong in _wrong_values(v):
                out.append((f"config {'.'.join(p)} = {wrong!r}",
                            tomli_w.dumps(edit(p, lambda t, k, w=wrong: t.__setitem__(k, w))).encode()))
            continue
        for bad in misspellings(p[-1], rng, 3):
            out.append((f"config {'.'.join(p)} misspelt {bad}",
                        tomli_w.dumps(edit(p, lambda t, k, b=bad: t.__setitem__(b, t.pop(k)))).encode()))
        v = _get(d, p)
        for wrong in _wrong_values(v):
            out.append((f"config {'.'.join(p)} = {wrong!r}",
                        tomli_w.dumps(edit(p, lambda t, k, w=wrong: t.__setitem__(k, w))).encode()))
    params = d.get("source", {}).get("params")
    if scenario_params and isinstance(params, dict):
        for k in list(params):
            for bad in misspellings(k, rng, 2):
                out.append((f"config source.params.{k} misspelt {bad}",
                            tomli_w.dumps(edit(("source", "params", k), lambda t, kk, b=bad: t.__setitem__(b, t.pop(kk)))).encode()))
            out.append((f"config source.params.{k} as a string",
                        tomli_w.dumps(edit(("source", "params", k), lambda t, kk: t.__setitem__(kk, "x"))).encode()))
    out.append(("config unknown table", (text + "\n[telemetry]\nenabled = true\n").encode()))
    out.append(("config unknown top-level key", ("mode = 1\n" + text).encode()))
    out.append(("config TOML unterminated string", re.sub(r'(?m)^(\w+ = )"([^"]*)"', r'\1"\2', text, count=1).encode()))
    out.append(("config TOML table header not closed", text.replace("[link]", "[link", 1).encode()))
    out.append(("config TOML duplicate table", (text + "\n[service]\n").encode()))
    out.append(("config non-UTF-8", text.encode().replace(b"[service]", b"[service]\n# \xff\xfe", 1)))
    out.append(("config cut inside a string", text[:text.index('"', text.index("[service]")) + 3].encode()))
    return out


FREE_KEY_TABLES = ("params", "slots")
"""Config tables whose keys the user names (scenario parameters are checked against the scenario;
CAN slots map any target id): a renamed key there is not a typo the loader can know."""


def _get(d: dict, path: tuple):
    for k in path:
        d = d[k]
    return d


def _wrong_values(v) -> list:
    """Values of another type that no key of that value's type may accept."""
    if isinstance(v, bool):
        return ["yes", 1.5]
    if isinstance(v, (int, float)):
        return ["fast", [v]]
    if isinstance(v, str):
        return [7, [v]]
    if isinstance(v, list):
        return ["x", {"a": 1}]
    if isinstance(v, dict):
        return [3, "table"]
    return []

