"""The session engine: one runner for every way frames reach the gateway.

Sources (live CAN buses, a recorded log, another tool's CAN log through :mod:`.canlog`, the
simulator's firmware) feed a :class:`Session`, which
owns the pipeline (drivers + estimator), the log time, raw-frame recording, the health cadence and
the end of input; sinks (the zenoh publisher, a recorder, an in-memory collector) take what it
emits. ``bsc gateway``, ``bsc replay``, ``bsc demo`` and the simulated series all run it, so live
and offline are the same code by construction.
"""
from .session import Session, Sink

__all__ = ["Session", "Sink"]
