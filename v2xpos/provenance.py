"""Provenance of a run, for every report / summary JSON: what software, which configs, which seeds, when.

Public API (stable)
-------------------
* ``provenance(command, configs=None, seeds=None, started_utc=None, argv=None) -> dict`` -- the
  ``"provenance"`` object of a report (layout below).
* ``software() -> dict`` -- {"name", "version", "git_revision", "git_dirty"} (git fields None when
  the package is not in a git checkout or git is unavailable; computed once per process).
* ``file_sha256(path) -> str``, ``config_digest(configs) -> (entries, combined_sha256)``.
* ``process_start_utc() -> datetime`` -- when this process started (Linux /proc; else the import
  time of this module).
* ``utc_iso(t)`` -- a datetime / Unix time as ISO 8601 UTC with a ``Z``.

Layout of the object (keys always present; values may be null)::

    {"command": "demo",
     "software": {"name": "v2xpos", "version": "0.1.0", "git_revision": "<40 hex>", "git_dirty": false},
     "python": "3.11.7",
     "configs": [{"name": "ego", "path": "out/demo/ego.toml", "sha256": "<64 hex>"},
                 {"name": "demo_arguments", "path": null, "sha256": "<64 hex>", "value": {...}}, ...],
     "configs_sha256": "<64 hex over the (name, sha256) pairs, sorted by name>",
     "seeds": {"scenario": 3},
     "started_utc": "2026-11-24T01:02:03.456Z", "written_utc": "...",
     "argv": ["v2xpos", "demo", "--seed", "3"]}

A config is a path (str or Path: the file's bytes are hashed; a missing file has sha256 null), bytes
(hashed as given) or a dict (hashed as canonical JSON: sorted keys, no spaces; also kept as
``value``). ``configs_sha256`` changes when any config changes, so two
reports with the same value ran the same configuration.
"""
from __future__ import annotations

import hashlib
import json
import os
import platform
import subprocess
import sys
import time
from datetime import datetime, timezone
from functools import lru_cache
from pathlib import Path
from typing import Any, Mapping, Sequence

_IMPORT_TIME_S = time.time()
PACKAGE_ROOT = Path(__file__).resolve().parents[1]


def utc_iso(t: datetime | float | None) -> str | None:
    """ISO 8601 UTC with millisecond precision and a trailing Z (None stays None)."""
    if t is None:
        return None
    if not isinstance(t, datetime):
        t = datetime.fromtimestamp(float(t), tz=timezone.utc)
    return t.astimezone(timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def process_start_utc() -> datetime:
    """Start time of this process: /proc/self/stat field 22 (clock ticks after boot) + boot time
    (/proc/stat ``btime``), Linux proc(5); elsewhere the import time of this module."""
    try:
        stat = Path("/proc/self/stat").read_text()
        fields = stat[stat.rindex(")") + 2:].split()
        start_ticks = int(fields[19])            # field 22 of proc(5); fields[0] is field 3
        btime = next(int(line.split()[1]) for line in Path("/proc/stat").read_text().splitlines()
                     if line.startswith("btime"))
        t = btime + start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, StopIteration, IndexError):
        t = _IMPORT_TIME_S
    return datetime.fromtimestamp(t, tz=timezone.utc)


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(["git", *args], cwd=PACKAGE_ROOT, capture_output=True, text=True, timeout=5)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


@lru_cache(maxsize=1)
def software() -> dict:
    """Package name and version; git revision and whether tracked files differ from it (dirty)
    when the package is in a git checkout."""
    from v2xpos import __version__
    rev = _git("rev-parse", "HEAD") if (PACKAGE_ROOT / ".git").exists() else None
    dirty = None
    if rev is not None:
        status = _git("status", "--porcelain", "--untracked-files=no")
        dirty = None if status is None else bool(status)
    return {"name": "v2xpos", "version": __version__, "git_revision": rev, "git_dirty": dirty}


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _config_entry(name: str, cfg: Any) -> dict:
    if isinstance(cfg, (str, Path)):
        p = Path(cfg)
        try:
            return {"name": name, "path": str(p), "sha256": file_sha256(p)}
        except OSError:
            return {"name": name, "path": str(p), "sha256": None}
    if isinstance(cfg, Mapping):
        text = json.dumps(cfg, sort_keys=True, separators=(",", ":"), default=str)
        return {"name": name, "path": None, "sha256": hashlib.sha256(text.encode()).hexdigest(),
                "value": json.loads(text)}
    if isinstance(cfg, (bytes, bytearray)):
        return {"name": name, "path": None, "sha256": hashlib.sha256(bytes(cfg)).hexdigest()}
    raise TypeError(f"config {name!r}: a path, bytes or dict, not {type(cfg).__name__}")


def config_digest(configs: Mapping[str, Any] | Sequence[Any] | None) -> tuple[list, str | None]:
    """([{"name", "path", "sha256"}, ...] sorted by name, combined SHA-256 or None without configs).

    ``configs``: {name: config} or a sequence of paths (named by their file name). The combined
    hash is SHA-256 over the lines ``name sha256`` (sorted by name)."""
    if not configs:
        return [], None
    items = configs.items() if isinstance(configs, Mapping) else ((Path(c).name, c) for c in configs)
    entries = sorted((_config_entry(str(n), c) for n, c in items), key=lambda e: e["name"])
    combined = hashlib.sha256("".join(f"{e['name']} {e['sha256']}\n" for e in entries).encode()).hexdigest()
    return entries, combined


def provenance(command: str, configs: Mapping[str, Any] | Sequence[Any] | None = None,
               seeds: Mapping[str, Any] | int | None = None, started_utc: datetime | float | None = None,
               argv: Sequence[str] | None = None) -> dict:
    """The ``"provenance"`` object of a report (module docstring). ``started_utc``: when the run
    started (datetime or Unix seconds; default: this process's start); ``seeds``: {name: seed} (an
    int is {"seed": n}); ``argv``: the command line (default ``sys.argv``)."""
    entries, combined = config_digest(configs)
    if isinstance(seeds, int) and not isinstance(seeds, bool):
        seeds = {"seed": seeds}
    return {"command": command, "software": dict(software()), "python": platform.python_version(),
            "configs": entries, "configs_sha256": combined, "seeds": dict(seeds or {}),
            "started_utc": utc_iso(process_start_utc() if started_utc is None else started_utc),
            "written_utc": utc_iso(time.time()), "argv": list(sys.argv if argv is None else argv)}
