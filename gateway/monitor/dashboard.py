"""A terminal dashboard of the live monitor: plain text, redrawn in place with ANSI codes.

:func:`render` is pure (snapshot -> text) so it is testable and usable with ``--once``; the
command clears the screen (``CLEAR``) before each frame only when stdout is a terminal. Every
line fits in ``WIDTH`` columns: a wider terminal gains nothing, a narrower one would wrap.

Tables, units in their headers: joints (friction fit of commanded - estimated torque), thruster
axes (estimated against commanded), devices (the drivers' health reports), buses (load) and
streams (efforts and commands, by when the monitor last received one), then the recent alerts,
at most two lines each.
"""
from __future__ import annotations

import math
import textwrap
import time

from gateway.efforts import Alert

from .core import STREAM_STALE_S

CLEAR = "\x1b[H\x1b[2J"
WIDTH = 120
ALERTS_SHOWN = 10
_RED, _YEL, _DIM, _OFF = "\x1b[31m", "\x1b[33m", "\x1b[2m", "\x1b[0m"


def _num(x, fmt: str) -> str:
    return f"{x:{fmt}}" if isinstance(x, (int, float)) and math.isfinite(x) else "-"


def _table(header: tuple[tuple[str, ...], ...], rows: list[tuple[str, tuple[str, ...]]], indent: str = "  "
           ) -> list[tuple[str, str]]:
    """Header lines (names, then units if apart) and ``(style, cells)`` rows -> ``(style, line)``: first
    column left-aligned, the others right-aligned, each as wide as its widest cell. Names too long
    for ``WIDTH`` lose their middle, never the numbers after them."""
    widths = [max(len(c) for c in col) for col in zip(*header, *(cells for _, cells in rows))]
    room = WIDTH - len(indent) - sum(widths[1:]) - 2 * (len(widths) - 1)
    if widths[0] > room:
        widths[0] = room
        rows = [(style, (_shorten(cells[0], room), *cells[1:])) for style, cells in rows]

    def line(cells):
        return indent + "  ".join(c.ljust(w) if i == 0 else c.rjust(w)
                                  for i, (c, w) in enumerate(zip(cells, widths))).rstrip()
    return [("", line(h)) for h in header] + [(style, line(cells)) for style, cells in rows]


def _shorten(name: str, width: int) -> str:
    if len(name) <= width:
        return name
    keep = max(width - 3, 2)
    return name[: keep - keep // 2] + "..." + name[-(keep // 2):]


def _clip(text: str, width: int = WIDTH) -> str:
    return text if len(text) <= width else text[: width - 3] + "..."


def _joints(joints: dict, hot) -> list[tuple[str, str]]:
    header = (("joint", "Coulomb", "of limit", "viscous", "offset", "|cmd - est|", "est/cmd"),
              ("", "[N m]", "[%]", "[N m s/rad]", "[N m]", "[N m]", ""))
    rows = []
    for name, m in joints.items():
        frac = m.get("friction_fraction", float("nan"))
        rows.append(("hot" if hot(name) else "", (
            name, _num(m["friction_nm"], ".1f"), _num(100 * frac, ".0f"), _num(m["viscous_nms"], ".1f"),
            _num(m["offset_nm"], ".1f"), _num(m["residual_nm"], ".1f"), _num(m["efficiency"], ".3f"))))
    return _table(header, rows)


def _axes(axes: dict, hot) -> list[tuple[str, str]]:
    # force axes in N, moment axes in N m: the unit goes with each row
    header = (("thruster axis", "est/cmd", "offset", "cmd rms", "|est - cmd|", "unit"),)
    rows = [("hot" if hot(axis) else "", (
        axis, _num(m["efficiency"], ".3f"), _num(m["offset"], ".1f"), _num(m["cmd_rms"], ".1f"),
        _num(m["residual"], ".1f"), "N" if axis.startswith("f") else "N m")) for axis, m in axes.items()]
    return _table(header, rows)


def _devices(devices: dict, hot) -> list[tuple[str, str]]:
    header = (("device", "stale [s]", "loss [%]", "samples", "lost"),)
    rows = [("hot" if hot(d) else "", (
        d, _num(m["staleness_s"], ".2f"), _num(100 * m["loss_rate"], ".2f"), _num(int(m["samples"]), "d"),
        _num(int(m["lost"]), "d"))) for d, m in devices.items()]
    return _table(header, rows)


def _buses(buses: dict, hot) -> list[tuple[str, str]]:
    rows = [("hot" if hot(f"bus/{b}") else "", (b, _num(100 * load, ".1f"))) for b, load in buses.items()]
    return _table((("bus", "load [%]"),), rows)


def _streams(streams: dict, hot) -> list[tuple[str, str]]:
    rows = []
    for st, age in streams.items():
        stale = isinstance(age, float) and math.isfinite(age) and age > STREAM_STALE_S
        rows.append(("hot" if hot(st) else "warn" if stale else "dim", (st, _num(age, ".2f"))))
    return _table((("stream", "last received [s ago]"),), rows)


def _alert_lines(a: Alert) -> list[str]:
    ev = ", ".join(f"{k}={v:.4g}" for k, v in a.evidence[:4])
    text = (f"{a.state:<7} {a.severity:<8} {a.robot}/{a.kind}/{a.target} [{a.rule}] {a.message}"
            + (f" ({ev})" if ev else ""))
    return textwrap.wrap(text, WIDTH - 2, subsequent_indent=" " * 17, max_lines=2, placeholder=" ...",
                         break_on_hyphens=False)


def render(snapshot: dict, alerts: list[Alert], *, color: bool = False, stats: dict | None = None,
           now_ns: int | None = None) -> str:
    styles = {"hot": _RED, "warn": _YEL, "dim": _DIM} if color else {}
    out: list[tuple[str, str]] = []         # (style, plain text): styled whole, after clipping

    def add(lines: list[tuple[str, str]]) -> None:
        out.extend(lines)

    clock = time.strftime("%H:%M:%S", time.localtime((now_ns or time.time_ns()) / 1e9))
    head = f"bsc monitor   {clock}"
    if stats:
        head += (f"   samples received {stats.get('received', 0)}, dropped {stats.get('dropped', 0)} (queue full), "
                 f"rejected {stats.get('rejected', 0)} (undecodable)")
    add([("", head)])
    if not snapshot:
        add([("", "(no robot seen yet: waiting for bsc/*/efforts, commands, health)")])
    for robot, s in snapshot.items():
        active = set(s["active"])

        def hot(target: str, active=active) -> bool:
            return any(a.endswith(":" + target) for a in active)

        title = f"== {robot}   " + (f"{len(active)} active alert(s)" if active else "no active alert")
        add([("", ""), ("hot" if active else "", title)])
        if s["flags"]:
            add([("dim", f"   flags: {' '.join(s['flags'])}")])
        for part, make in (("joints", _joints), ("axes", _axes), ("devices", _devices), ("buses", _buses),
                           ("streams", _streams)):
            if s.get(part):
                add(make(s[part], hot))
    if alerts:
        add([("", ""), ("", f"recent alerts (last {min(len(alerts), ALERTS_SHOWN)} of {len(alerts)}):")])
        for a in alerts[-ALERTS_SHOWN:]:
            raised = a.state == "raised"
            style = "hot" if raised and a.severity == "critical" else "warn" if raised else "dim"
            add([(style, "  " + line) for line in _alert_lines(a)])
    text = []
    for style, line in out:
        line = _clip(line)
        text.append(f"{styles[style]}{line}{_OFF}" if style in styles else line)
    return "\n".join(text) + "\n"
