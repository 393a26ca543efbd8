"""A terminal dashboard of the live monitor: plain text, redrawn in place with ANSI codes.

:func:`render` is pure (snapshot -> text) so it is testable and usable with ``--once``; the
command clears the screen (``CLEAR``) before each frame only when stdout is a terminal.
"""
from __future__ import annotations

import math
import time

from gateway.efforts import Alert

CLEAR = "\x1b[H\x1b[2J"
_RED, _YEL, _DIM, _OFF = "\x1b[31m", "\x1b[33m", "\x1b[2m", "\x1b[0m"


def _f(x, fmt: str = "8.1f") -> str:
    width = int(fmt.split(".")[0]) if fmt[0].isdigit() else 8
    return f"{x:{fmt}}" if isinstance(x, float) and math.isfinite(x) else " " * (width - 1) + "-"


def render(snapshot: dict, alerts: list[Alert], *, color: bool = False, stats: dict | None = None,
           now_ns: int | None = None) -> str:
    red, yel, dim, off = (_RED, _YEL, _DIM, _OFF) if color else ("", "", "", "")
    lines = [f"bsc monitor   {time.strftime('%H:%M:%S', time.localtime((now_ns or time.time_ns()) / 1e9))}"
             + (f"   received {stats.get('received', 0)}  dropped {stats.get('dropped', 0)}"
                f"  rejected {stats.get('rejected', 0)}" if stats else "")]
    if not snapshot:
        lines.append("(no robot seen yet: waiting for bsc/*/efforts, commands, health)")
    for robot, s in snapshot.items():
        active = set(s["active"])
        lines.append("")
        lines.append(f"== {robot}" + (f"   {red}{len(active)} active alert(s){off}" if active else "   no active alert")
                     + (f"   {dim}flags: {' '.join(s['flags'])}{off}" if s["flags"] else ""))
        if s["joints"]:
            lines.append(f"  {'joint':<10} {'friction':>9} {'of limit':>9} {'viscous':>8} {'offset':>8}"
                         f" {'|resid|':>8} {'effic.':>7}")
            for name, m in s["joints"].items():
                hot = any(a.endswith(":" + name) for a in active)
                mark = red if hot else ""
                frac = m.get("friction_fraction", float("nan"))
                lines.append(f"{mark}  {name:<10} {_f(m['friction_nm'], '9.1f')} "
                             f"{(f'{frac:8.0%}' if math.isfinite(frac) else '       -')}  {_f(m['viscous_nms'])} "
                             f"{_f(m['offset_nm'])} {_f(m['residual_nm'])} {_f(m['efficiency'], '7.3f')}{off if hot else ''}")
        if s["axes"]:
            lines.append(f"  {'thruster':<10} {'effic.':>9} {'offset':>9} {'cmd rms':>8} {'|resid|':>8}")
            for axis, m in s["axes"].items():
                hot = any(a.endswith(":" + axis) for a in active)
                mark = red if hot else ""
                lines.append(f"{mark}  {axis:<10} {_f(m['efficiency'], '9.3f')} {_f(m['offset'], '9.1f')} "
                             f"{_f(m['cmd_rms'])} {_f(m['residual'])}{off if hot else ''}")
        if s["devices"] or s["buses"] or s["streams"]:
            lines.append(f"  {'sensor':<22} {'stale s':>8} {'loss':>8} {'samples':>9}")
            for d, m in s["devices"].items():
                lines.append(f"  {d:<22} {_f(m['staleness_s'], '8.2f')} {_f(m['loss_rate'], '8.2%')} "
                             f"{int(m['samples']):>9}")
            for b, load in s["buses"].items():
                lines.append(f"  {'bus/' + b:<22} load {load:6.1%}")
            for st, age in s["streams"].items():
                stale = isinstance(age, float) and math.isfinite(age) and age > 1.0
                lines.append(f"  {(yel if stale else dim)}{st:<22} last {_f(age, '8.2f')} s ago{off}")
    if alerts:
        lines.append("")
        lines.append("recent alerts:")
        for a in alerts[-10:]:
            c = red if a.state == "raised" and a.severity == "critical" else yel if a.state == "raised" else dim
            ev = ", ".join(f"{k}={v:.4g}" for k, v in a.evidence[:4])
            lines.append(f"  {c}{a.state:<7} {a.severity:<8} {a.robot}/{a.kind}/{a.target} [{a.rule}] "
                         f"{a.message}  ({ev}){off}")
    return "\n".join(lines) + "\n"
