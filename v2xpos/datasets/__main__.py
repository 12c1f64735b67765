"""``python -m v2xpos.datasets PATH [--raw]``: load a dataset and print its summary as JSON."""
from __future__ import annotations

import argparse
import json
import sys

from v2xpos.datasets.loader import describe, load_dataset


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m v2xpos.datasets", description=__doc__)
    parser.add_argument("path", help="dataset.toml or dataset folder")
    parser.add_argument("--raw", action="store_true", help="also read the raw GNSS stream (UBX)")
    args = parser.parse_args(argv)
    try:
        ds = load_dataset(args.path, read_raw=args.raw)
    except (ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(describe(ds), indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
