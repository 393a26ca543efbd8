"""The terminal dashboard: units in every header, rows that fill the columns their header
promises, and nothing wider than the 120 columns it is drawn for."""
from __future__ import annotations

import math
import re

import pytest

from drivers.samples import BusHealth, DeviceHealth
from gateway import keys
from gateway.efforts import Alert, JointEfforts
from gateway.monitor.core import Monitor
from gateway.monitor.dashboard import WIDTH, render
from gateway.monitor.rules import Rule, RuleSet

ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")
LONG_JOINT = "left_manipulator/elbow_pitch_actuator"


def _monitor() -> Monitor:
    mon = Monitor(RuleSet((Rule("loss", "sensor", "loss_rate", 0.01, 0.002),)), limits=None)
    for t, samples, lost in ((1_000_000_000, 1000, 0), (2_000_000_000, 1900, 100)):
        mon.feed(keys.device_health("r1", "arm0"),
                 DeviceHealth("arm0", "arm0", t, samples, lost, 0, (), t - 1_500_000, False), recv_ns=t)
    mon.feed(keys.bus_health("r1", "arm0"), BusHealth("arm0", 2_000_000_000, 5000, (), 0.596), recv_ns=2_000_000_000)
    for k in range(400):                    # 4 s of a joint moving both ways, 100 Hz
        t = 2_000_000_000 + k * 10_000_000
        rate = 0.3 * math.sin(k / 20)
        est = 50.0 - 30.0 * math.copysign(1.0, rate)
        je = JointEfforts("left_manipulator", t, (LONG_JOINT,), (est,), (est,), (50.0,), t, (rate,), True)
        mon.feed(keys.joint_efforts("r1", "left_manipulator"), je, recv_ns=t)
    return mon


def _row(text: str, first: str, below: int = 0) -> list[str]:
    """The words of the line that starts with ``first`` (or of the ``below``-th line after it)."""
    lines = text.splitlines()
    i = next(i for i, line in enumerate(lines) if line.split()[:1] == [first])
    return lines[i + below].split()


def test_headers_carry_units_and_rows_fill_every_column():
    mon = _monitor()
    text = render(mon.snapshot(6_500_000_000), mon.recent, now_ns=6_500_000_000)
    assert _row(text, "joint") == ["joint", "Coulomb", "of", "limit", "viscous", "offset", "|cmd", "-", "est|",
                                   "est/cmd"]
    assert _row(text, "joint", below=1) == ["[N", "m]", "[%]", "[N", "m", "s/rad]", "[N", "m]", "[N", "m]"]
    header = _row(text, "device")
    assert header == ["device", "stale", "[s]", "loss", "[%]", "samples", "lost"]
    # arm0: its last sample 1.5 ms before the report, 100 of 1000 lost since the previous report
    assert _row(text, "arm0") == ["arm0", "0.00", "10.00", "1900", "100"]
    assert _row(text, "bus") == ["bus", "load", "[%]"] and "59.6" in text
    assert _row(text, "stream") == ["stream", "last", "received", "[s", "ago]"]
    assert _row(text, "efforts/joints/left_manipulator") == ["efforts/joints/left_manipulator", "0.51"]
    assert "s ago" not in text.replace("[s ago]", "")        # the old rows' wording, under another header
    coulomb = _row(text, LONG_JOINT)[1]
    assert float(coulomb) == pytest.approx(30.0, abs=0.5)


def test_long_names_keep_columns_aligned():
    mon = _monitor()
    text = render(mon.snapshot(6_500_000_000), mon.recent, now_ns=6_500_000_000)
    lines = text.splitlines()
    head = next(line for line in lines if line.lstrip().startswith("joint"))
    row = next(line for line in lines if LONG_JOINT in line)
    # right-aligned columns: the header's last column ends where the row's does
    assert len(head) == len(row)
    assert head.index("Coulomb") > row.index(LONG_JOINT) + len(LONG_JOINT)


def test_every_line_fits_120_columns_and_alerts_wrap_at_most_twice():
    mon = _monitor()
    long_msg = "joint friction far above its baseline " * 8
    alerts = [Alert("r1", "actuator", LONG_JOINT, "joint-friction-high", "critical", "raised", 1, 2, long_msg,
                    (("friction_nm", 182.0), ("threshold_nm", 150.0))),
              Alert("r1", "sensor", "arm0", "loss", "warning", "cleared", 1, 3, "loss rate back under 0.2 %")]
    for color in (False, True):
        text = render(mon.snapshot(6_500_000_000), alerts, color=color, now_ns=6_500_000_000,
                      stats={"received": 123456789, "dropped": 0, "rejected": 0})
        plain = ANSI.sub("", text)
        widest = max(plain.splitlines(), key=len)
        assert len(widest) <= WIDTH, widest
    lines = plain.splitlines()
    first = next(i for i, line in enumerate(lines) if "[joint-friction-high]" in line)
    assert lines[first + 1].startswith(" " * 19) and lines[first + 1].endswith("...")
    assert lines[first + 2].lstrip().startswith("cleared")
    assert "\x1b[31m" in text                                  # the critical alert in red, when colour is on
