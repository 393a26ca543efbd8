"""``bsc demo``: the main job, with no external server.

For now (the estimator service is not wired yet) it runs the paper's capture scenario in the
simulator and writes the truth trace and the paper-like figures to ``--out`` (default
``./bsc-demo``), exactly as ``bsc sim`` does with the demo's defaults.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from . import sim


def add_arguments(p: argparse.ArgumentParser) -> None:
    sim.add_arguments(p)
    p.set_defaults(out=Path("bsc-demo"))


def run(args: argparse.Namespace) -> int:
    return sim.run(args)
