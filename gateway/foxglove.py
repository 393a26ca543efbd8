"""Foxglove's well-known message types for what bsc records, so that Foxglove's own panels show it
without configuration (its Log panel takes ``foxglove.Log`` messages on any topic).

An alert is recorded twice by ``bsc record``: as itself on its zenoh key (``gateway.efforts.Alert``,
every field, what bsc reads back) and as a ``foxglove.Log`` line on :data:`ALERT_LOG_TOPIC`. The
schema below is written for bsc from Foxglove's documented message definition; the Foxglove tier
of CI validates these messages against the published schema (npm ``@foxglove/schemas``).
"""
from __future__ import annotations

from typing import Any

ALERT_LOG_TOPIC = "/foxglove/alerts"
LOG_SCHEMA_NAME = "foxglove.Log"

# foxglove.LogLevel: 0 unknown, 1 debug, 2 info, 3 warning, 4 error, 5 fatal
_LEVEL = {"info": 2, "warning": 3, "critical": 4}

LOG_SCHEMA: dict[str, Any] = {
    "title": LOG_SCHEMA_NAME,
    "description": "A log line (Foxglove's Log panel): a bsc alert raised or cleared",
    "type": "object",
    "properties": {
        "timestamp": {"type": "object", "title": "time", "description": "when the alert changed state (sensor time)",
                      "properties": {"sec": {"type": "integer", "minimum": 0},
                                     "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}}},
        "level": {"type": "integer", "minimum": 0, "maximum": 5,
                  "description": "2 info (a cleared alert), 3 warning, 4 error (critical)"},
        "message": {"type": "string"},
        "name": {"type": "string", "description": "bsc/<robot>/<kind>/<target> [<rule>]"},
        "file": {"type": "string"},
        "line": {"type": "integer", "minimum": 0},
    },
    "required": ["timestamp", "level", "message", "name", "file", "line"],
}


def alert_log(alert) -> dict[str, Any]:
    """The ``foxglove.Log`` message of a :class:`gateway.efforts.Alert`: a raised alert at its
    severity's level, a cleared one at info."""
    sec, nsec = divmod(max(0, int(alert.t_ns)), 1_000_000_000)
    level = _LEVEL.get(alert.severity, 0) if alert.state == "raised" else _LEVEL["info"]
    return {"timestamp": {"sec": sec, "nsec": nsec}, "level": level,
            "message": f"{alert.state} {alert.severity}: {alert.message}",
            "name": f"bsc/{alert.robot}/{alert.kind}/{alert.target} [{alert.rule}]", "file": "", "line": 0}
