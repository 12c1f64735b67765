"""``v2xpos keys``: generate vehicle signing keys and manage the master's trust list (the files
are described in ``v2xpos.security`` and docs/security.md)."""
from __future__ import annotations

import argparse
import sys

from v2xpos.security import (TrustFileError, TrustList, generate_vehicle_key, load_public_key_file,
                             load_trust_list)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="keys_command", required=True)
    gen = sub.add_parser("gen", help="generate a vehicle's Ed25519 key pair")
    gen.add_argument("--vehicle", required=True, help="vehicle id (1-64 chars of [A-Za-z0-9_.-])")
    gen.add_argument("--out", required=True, help="directory for <vehicle>.key and <vehicle>.pub")
    gen.add_argument("--force", action="store_true", help="replace existing files")
    gen.add_argument("--trust", help="also add the public key to this trust list")
    trust = sub.add_parser("trust", help="manage the master's trust list")
    tsub = trust.add_subparsers(dest="trust_command", required=True)
    add = tsub.add_parser("add", help="add public keys (.pub files) to the trust list")
    add.add_argument("--trust", required=True, help="trust list JSON file (created if missing)")
    add.add_argument("pub", nargs="+", help=".pub files")
    rm = tsub.add_parser("remove", help="remove keys by vehicle id or key id")
    rm.add_argument("--trust", required=True)
    rm.add_argument("--vehicle")
    rm.add_argument("--key-id")
    ls = tsub.add_parser("list", help="list trusted keys")
    ls.add_argument("--trust", required=True)
    ls.add_argument("--json", action="store_true", help="print the file's JSON")


def run(args: argparse.Namespace) -> int:
    try:
        if args.keys_command == "gen":
            files = generate_vehicle_key(args.vehicle, args.out, overwrite=args.force)
            print(f"{files.vehicle_id}: key id {files.key_id}\n  private {files.private_path}\n"
                  f"  public  {files.public_path}")
            if args.trust:
                trust = load_trust_list(args.trust, missing_ok=True)
                vid, pub = load_public_key_file(files.public_path)
                trust.add(vid, pub)
                trust.save(args.trust)
                print(f"  trusted in {args.trust}")
            return 0
        if args.trust_command == "add":
            trust = load_trust_list(args.trust, missing_ok=True)
            _print_issues(trust)
            failed = 0
            for p in args.pub:
                try:
                    vid, pub = load_public_key_file(p)
                except TrustFileError as exc:
                    print(f"error: {exc}", file=sys.stderr)
                    failed += 1
                    continue
                entry = trust.add(vid, pub)
                print(f"trusted {entry.vehicle_id} (key id {entry.key_id})")
            trust.save(args.trust)
            return 1 if failed else 0
        if args.trust_command == "remove":
            if not args.vehicle and not args.key_id:
                print("error: give --vehicle or --key-id", file=sys.stderr)
                return 2
            trust = load_trust_list(args.trust)
            _print_issues(trust)
            n = trust.remove(args.vehicle, args.key_id)
            trust.save(args.trust)
            print(f"removed {n} key(s)")
            return 0 if n else 1
        trust = load_trust_list(args.trust)
        _print_issues(trust)
        if args.json:
            print(trust.to_json(), end="")
        else:
            for e in sorted(trust.entries.values(), key=lambda e: e.vehicle_id):
                print(f"{e.vehicle_id:<24} {e.key_id}  {e.added_utc}")
        return 0
    except (TrustFileError, FileExistsError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1


def _print_issues(trust: TrustList) -> None:
    for issue in trust.issues:
        print(f"warning: skipped {issue}", file=sys.stderr)
