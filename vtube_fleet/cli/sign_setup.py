"""``vtube-fleet sign-setup``: provision each vehicle's MAVLink 2 signing key (SETUP_SIGNING)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from vtube_fleet.cli._args import DURATION, bounded
from vtube_fleet.link.signing import run_sign_setup

__all__ = ["register"]


def _cmd_sign_setup(args: argparse.Namespace) -> int:
    urls = [u.strip() for u in args.endpoints.split(",") if u.strip()]
    done = run_sign_setup(args.mission, urls, timeout_s=args.timeout, generate=args.generate,
                          current_key_file=args.current_key)
    for r in done:
        print(f"{r.endpoint}: vehicle {r.sysid} signs with {r.key_file} (initial timestamp "
              f"{r.timestamp})")
    print(f"{len(done)} vehicle(s) provisioned; fly them with the mavlink backend")
    return 0


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "sign-setup",
        help="provision the mission's MAVLink 2 signing key on each vehicle (disarmed)",
        description="Send each vehicle (endpoint i = slot i) its key from the mission's "
        "[mission].signing_key_file with SETUP_SIGNING, then check that it signs with it "
        "(a signed HEARTBEAT). Refused while a vehicle is armed, as PX4 refuses. "
        "See docs/security.md.",
    )
    p.add_argument("mission", type=Path, help="mission file with [mission].signing_key_file")
    p.add_argument("--endpoints", required=True, metavar="URL,URL,...",
                   help="the vehicles' MAVLink endpoints (udpin://HOST:PORT, udpout://…)")
    p.add_argument("--timeout", type=bounded(DURATION), default=10.0,
                   help="seconds to wait for each vehicle (default 10)")
    p.add_argument("--generate", action="store_true",
                   help="create missing key files (32 random bytes, mode 0600) first")
    p.add_argument("--current-key", default=None, metavar="FILE",
                   help="the key the vehicles hold now (rotation: PX4 takes a new key only "
                   "signed with the current one)")
    p.set_defaults(func=_cmd_sign_setup)
