"""What ``bsc demo`` prints and how it ends: the accuracy tables, what is judged, the exit status."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from harness import demo
from gateway.cli import EXIT_OK, EXIT_TARGETS_MISSED
from harness.commands.demo import exit_status

N = 2000
JOINTS = ["arm0/j1", "arm0/j2", "left_manipulator/shoulder_yaw", "left_manipulator/elbow_pitch_actuator"]
FIRST = {"arm0/j1", "left_manipulator/shoulder_yaw"}


def _case(full_error: float = 0.001, fired: bool = True):
    """Truth and estimates of a run: thruster axes with a known peak, mx small (below 5 % of the
    largest moment), joints whose simplified estimate is far off away from the sensor."""
    t = np.arange(N) / 1000.0
    wave = np.sin(2 * np.pi * 0.5 * t)
    thr_act = np.outer(wave, [200.0, 250.0, 90.0, 8.0, 200.0, 760.0]) * fired
    tau_act = np.outer(wave, [600.0, 170.0, 400.0, 30.0])
    rng = np.random.default_rng(0)
    thrusters = thr_act + rng.normal(0, 0.001, thr_act.shape) * [200, 250, 90, 8, 200, 760]
    full = tau_act * (1 + full_error)
    simplified = tau_act.copy()
    simplified[:, [1, 3]] *= 1.4                       # links between sensor and joint neglected
    est = demo.Estimates(thrusters, full, simplified, np.ones(N, bool), N)
    trace = SimpleNamespace(arrays={"thr_act": thr_act, "tau_act": tau_act})
    return demo.accuracy(trace, est, JOINTS, FIRST)


def _row(table: str, first: str) -> str:
    return next(line for line in table.splitlines() if line.startswith(first + " "))


def test_table_columns_stay_aligned_with_long_joint_names_and_torques_in_n_m():
    table = demo.format_table(_case())
    header = _row(table, "joint")
    rows = [_row(table, name) for name in JOINTS]
    # the numbers of every row end where the header's columns end
    for word in ("simplified", "full"):
        end = header.index(word) + len(word)
        assert all(row[end - 1] == "%" for row in rows), (word, rows)
    assert all(row.index("N m") == rows[0].index("N m") for row in rows)
    assert "Nm" not in table and "N·m" not in table
    assert _row(table, "mx").split()[-1] == "moment"       # 'no: peak below 5 % of the largest moment'


def test_table_says_which_simplified_figures_are_judged():
    table = demo.format_table(_case())
    for name in JOINTS:
        simplified = _row(table, name).split()[3]
        assert simplified == ("judged" if name in FIRST else "reported"), name
    assert "judged on each arm's first" in table and "reported on the others" in table


def test_a_miss_is_exit_status_3_unless_report_only():
    good, bad = _case(), _case(full_error=0.05)
    assert good["pass"] and exit_status(good) == EXIT_OK
    assert not bad["pass"] and exit_status(bad) == EXIT_TARGETS_MISSED == 3
    assert exit_status(bad, report_only=True) == EXIT_OK
    # 5 % of a sine wave: an RMS error of 5 % / sqrt(2) of its peak
    assert demo.missed(bad) == [f"{name} full 3.54 % > 2 %" for name in JOINTS]
    assert demo.missed(good) == []
    assert "MISSED" in _row(demo.format_table(bad), "arm0/j2")


def test_axes_that_never_fired_are_not_judged():
    acc = _case(fired=False)
    assert not any(s["judged"] for s in acc["thrusters"].values())
    assert acc["pass"]
    row = demo.summary_row(acc)
    assert math.isnan(row["force_nrmse_max"]) and math.isnan(row["moment_nrmse_max"])
    assert "no: never fired" in _row(demo.format_table(acc), "fx")


def test_spacecraft_outline_comes_from_the_robot():
    import robot_description
    from simulator.plots import spacecraft_radius

    paper = robot_description.load("paper_robot").urdf
    assert spacecraft_radius(paper) == (pytest.approx(2.1), "arm mounts")          # the paper's 4.2 m
    assert spacecraft_radius(robot_description.load("three_arm").urdf) == (pytest.approx(1.6), "arm mounts")
    drawn = paper.replace('<link name="spacecraft">', '<link name="spacecraft"><visual><geometry>'
                          '<cylinder radius="2.5" length="2"/></geometry></visual>', 1)
    assert spacecraft_radius(drawn) == (2.5, "URDF cylinder")
