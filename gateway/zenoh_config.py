"""Explicit zenoh configuration, shared by every ``bsc`` command that opens a session.

Options (as zenoh's own examples take them)::

    --zenoh-config FILE.json5   a zenoh configuration file, read first
    --mode peer|client|router
    --connect ENDPOINT       (repeatable) e.g. tcp/127.0.0.1:7447
    --listen ENDPOINT        (repeatable) e.g. tcp/127.0.0.1:7447
    --multicast-scouting     allow multicast scouting (off unless asked for)

Flags override the file. Unless the file or ``--listen`` says otherwise, nothing listens:
zenoh's default would listen on every interface. Multicast scouting is off unless the flag
is given (a file cannot silently turn it on for a command that did not ask).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Sequence


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("zenoh")
    g.add_argument("--zenoh-config", metavar="FILE.json5", type=Path, default=None,
                   help="zenoh configuration file (JSON5), e.g. deploy/zenoh/gateway.json5")
    g.add_argument("--mode", choices=("peer", "client", "router"), help="session mode (default: peer)")
    g.add_argument("--connect", metavar="ENDPOINT", action="append", default=[],
                   help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
    g.add_argument("--listen", metavar="ENDPOINT", action="append", default=[],
                   help="endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable)")
    g.add_argument("--multicast-scouting", action="store_true", help="allow multicast scouting (default off)")


def make_config(connect: Sequence[str] = (), listen: Sequence[str] = (), config_file: str | Path | None = None,
                mode: str | None = None, multicast_scouting: bool = False):
    """A ``zenoh.Config`` built only from what is given here."""
    import zenoh

    if config_file is not None:
        path = Path(config_file)
        if not path.is_file():
            raise FileNotFoundError(f"no zenoh config file {path}")
        conf = zenoh.Config.from_file(str(path))
    else:
        conf = zenoh.Config()
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if mode:
        conf.insert_json5("mode", json.dumps(mode))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("scouting/multicast/enabled", "true" if multicast_scouting else "false")
    return conf


def config_from_args(args: argparse.Namespace):
    return make_config(connect=args.connect, listen=args.listen, config_file=args.zenoh_config, mode=args.mode,
                       multicast_scouting=args.multicast_scouting)


def free_port() -> int:
    """A TCP port on loopback that nothing listens on now, chosen by the OS (for a zenoh endpoint
    of a test, a benchmark or the demo; another process may take it before it is used)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
