"""``bsc bench``: run every benchmark and print one table (the suite of ``benchmarks/``).

Each figure is printed beside an anchor measured in the same run (cantools per-frame decode, a
raw zenoh round trip, a python-can virtual bus, numpy batched products) and the ratio between
them, with its target; the header gives date, machine, load average and versions. The same
as ``python -m benchmarks`` (benchmarks/suite.py); ``--json`` for machines.

The benchmarks live in the source tree (``benchmarks/`` beside ``gateway/``), not in the
installed distribution: a top-level package named ``benchmarks`` in site-packages would shadow
anyone else's. ``bsc bench`` therefore needs a source checkout (the README's editable install).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _suite():
    try:
        from benchmarks import suite
    except ImportError:
        root = Path(__file__).resolve().parents[2]
        if not (root / "benchmarks" / "suite.py").is_file():
            from gateway.cli import UserError

            raise UserError(f"bsc bench needs the source tree: no benchmarks/ beside {root / 'gateway'} "
                            "(install bsc from a git checkout with pip install -e .)") from None
        sys.path.insert(0, str(root))
        sys.modules.pop("benchmarks", None)
        from benchmarks import suite
    return suite


def add_arguments(parser: argparse.ArgumentParser) -> None:
    _suite().add_arguments(parser)


def run(args: argparse.Namespace) -> int:
    return _suite().run_args(args)
