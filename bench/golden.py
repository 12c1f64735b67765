"""Golden check: the figures a refactoring must keep byte-identical.

``python -m bench.golden --write DIR`` records, from the code in the current directory,

- ``v2xpos replay --json --solution`` on ``drive_0708`` and ``convoy_dev/A`` (the summary JSON without
  the keys that measure the machine or the run -- wall-clock and CPU time, throughput, provenance --
  and the solution CSV);
- ``v2xpos convoy --in-process`` on ``convoy_dev`` A + B (``results.csv``);

``--check DIR`` runs the same and compares every file byte for byte with the recorded one (exit 0:
identical, 1: a file differs or is missing, naming it). Each command runs as a subprocess of this
interpreter (``python -m v2xpos``), so it measures the code of the working tree it is run from.
"""
from __future__ import annotations

import argparse
import filecmp
import json
import subprocess
import sys
import tempfile
from pathlib import Path

DATA = Path("../shared/data")
REPLAYS = {"drive_0708": DATA / "drive_0708" / "dataset.toml", "convoy_dev_A": DATA / "convoy_dev" / "A" / "dataset.toml"}
CONVOY = (DATA / "convoy_dev" / "A" / "dataset.toml", DATA / "convoy_dev" / "B" / "dataset.toml")
RUN_DEPENDENT_KEYS = frozenset({"wall_s", "imu_samples_per_s", "provenance", "cpu_s", "forward_s", "backward_s"})
"""Summary keys that measure the machine or the invocation, not the result."""


def _without_run_keys(value):
    """``value`` with every dict key in ``RUN_DEPENDENT_KEYS`` (at any depth) removed."""
    if isinstance(value, dict):
        return {k: _without_run_keys(v) for k, v in value.items() if k not in RUN_DEPENDENT_KEYS}
    if isinstance(value, list):
        return [_without_run_keys(v) for v in value]
    return value


def _run(args: list[str], log: Path) -> None:
    cmd = [sys.executable, "-m", "v2xpos", *args]
    with log.open("w") as f:
        rc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT).returncode
    if rc != 0:
        raise SystemExit(f"golden: {' '.join(cmd)} exited {rc} (log {log})")


def write(out: Path) -> list[Path]:
    """Run every golden command, write the compared files into ``out``; returns them."""
    out.mkdir(parents=True, exist_ok=True)
    files = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp_dir = Path(tmp)
        for name, ds in REPLAYS.items():
            raw = tmp_dir / f"{name}.json"
            sol = out / f"replay_{name}_solution.csv"
            _run(["replay", str(ds), "--no-progress", "--json", str(raw), "--solution", str(sol)],
                 tmp_dir / f"{name}.log")
            summary = _without_run_keys(json.loads(raw.read_text()))
            js = out / f"replay_{name}.json"
            js.write_text(json.dumps(summary, indent=1, sort_keys=True) + "\n")
            files += [js, sol]
        conv = tmp_dir / "convoy"
        _run(["convoy", *map(str, CONVOY), "--in-process", "--out", str(conv)], tmp_dir / "convoy.log")
        res = out / "convoy_results.csv"
        res.write_bytes((conv / "results.csv").read_bytes())
        files.append(res)
    return files


def check(golden: Path) -> int:
    """Run into a temporary directory and compare with ``golden``; 0 identical, 1 otherwise."""
    with tempfile.TemporaryDirectory() as tmp:
        files = write(Path(tmp))
        bad = [f.name for f in files if not (golden / f.name).is_file()
               or not filecmp.cmp(f, golden / f.name, shallow=False)]
    for name in bad:
        print(f"golden: {name} differs from {golden / name}")
    if not bad:
        print(f"golden: {len(files)} files identical to {golden}")
    return 1 if bad else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.golden", description=__doc__.split("\n\n")[0])
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--write", metavar="DIR", help="record the golden files into DIR")
    group.add_argument("--check", metavar="DIR", help="compare with the golden files in DIR")
    args = parser.parse_args(argv)
    if args.write:
        for f in write(Path(args.write)):
            print(f"golden: wrote {f}")
        return 0
    return check(Path(args.check))


if __name__ == "__main__":
    sys.exit(main())
