"""``vtube-fleet bus-setup``: certificates, passwords, ACL and mosquitto.conf of a mission."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from vtube_fleet.cli._args import COUNT, PORT, bounded
from vtube_fleet.fleet.distributed.coordinator import mission_bus_setup

__all__ = ["register"]


def _cmd_bus_setup(args: argparse.Namespace) -> int:
    s = mission_bus_setup(
        args.mission, args.out, mission_id=args.mission_id, vehicles=args.vehicles,
        hosts=args.host, port=args.port, bind=args.bind,
        plain_loopback_port=args.plain_loopback, days=args.days,
        passwd_tool=None if args.builtin_hash else "auto",
    )
    host = s.hosts[-1]
    print(f"bus setup of mission {s.mission_id} ({s.vehicles} vehicles) in {s.out}:")
    print(f"  broker:      mosquitto -c {s.conf}   (TLS on port {s.port}"
          + (f", plain on 127.0.0.1:{s.plain_loopback_port}" if s.plain_loopback_port else "")
          + ")")
    print(f"  certificate: {s.out / 'server.crt'} for {', '.join(s.hosts)}; CA {s.ca_file} "
          f"(keep {s.out / 'ca.key'} offline)")
    print(f"  passwords:   {s.passwd} (hashed by {s.hashed_by}); ACL {s.acl}")
    print(f"  agent I:     vtube-fleet agent {args.mission} --vehicle I --broker "
          f"mqtts://{host}:{s.port} --credentials {s.out / 'credentials'}/vehicle-I.toml")
    print(f"  coordinator: vtube-fleet mission start {args.mission} --broker "
          f"mqtts://{host}:{s.port} --credentials {s.coordinator_credentials}")
    print("  copy each vehicle's credentials file (and ca.crt) to its companion computer only")
    return 0


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "bus-setup",
        help="write a secured mosquitto setup for a mission: TLS, passwords, ACL",
        description="Write into a new directory everything a mosquitto broker of MISSION needs: "
        "a CA and server certificate, one password per vehicle and the coordinator "
        "(credentials/*.toml), an ACL (vehicle I publishes only its own state and status, only "
        "the coordinator publishes config and commands) and mosquitto.conf with a TLS "
        "listener. See docs/security.md.",
    )
    p.add_argument("mission", type=Path, help="mission file (scenario + [mission])")
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="a new (or empty) directory for the files")
    p.add_argument("--mission-id", default=None,
                   help="topic name of the mission (default: the file name)")
    p.add_argument("--vehicles", type=bounded(COUNT), default=None,
                   help="credentials for slots 0..N-1 (default: every slot)")
    p.add_argument("--host", action="append", default=[], metavar="NAME",
                   help="a name or address clients use for the broker, put in its certificate "
                   "(repeatable; localhost and 127.0.0.1 always are)")
    p.add_argument("--port", type=bounded(PORT), default=8883,
                   help="TLS listener port (default 8883)")
    p.add_argument("--bind", default=None, metavar="ADDR",
                   help="TLS listener address (default: every interface)")
    p.add_argument("--plain-loopback", type=bounded(PORT), default=None, metavar="PORT",
                   help="also a plain MQTT listener on 127.0.0.1:PORT (never on the network)")
    p.add_argument("--days", type=bounded(COUNT), default=365,
                   help="certificate validity in days (default 365)")
    p.add_argument("--builtin-hash", action="store_true",
                   help="hash the passwords in Python (mosquitto's $7$ format) instead of "
                   "with mosquitto_passwd")
    p.set_defaults(func=_cmd_bus_setup)
