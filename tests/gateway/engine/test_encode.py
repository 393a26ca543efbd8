"""JSON written straight from rows is byte for byte the JSON of the objects, in the one form of a
record: the zenoh payloads (gateway.codec.encode) and the log's messages (gateway.log.schema) are
the same bytes, for every sample kind and every effort, with flags, commands missing and present,
several robots."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from gateway import codec
from gateway.engine.encode import EffortJson, SampleJson
from gateway.log.schema import dataclass_json

sys.path.insert(0, str(Path(__file__).parents[1] / "estimator"))
from test_core import _samples  # noqa: E402

from drivers.kernel import DriverCore  # noqa: E402
from drivers.wire import WireMap  # noqa: E402
from gateway.estimator import core as ecore  # noqa: E402
from simulator import firmware  # noqa: E402


def _python(objs, form):
    """The objects' JSON by the zenoh codec or by the log's encoder (the same form)."""
    if form == "zenoh":
        return [codec.encode(o) for o in objs]
    return [dataclass_json(type(o))(o).encode() for o in objs]


@pytest.fixture(scope="module", params=["capture", "three_arm"])
def run(request):
    faults = firmware.Faults(drop_rate=0.02, silent=(("imu", 0.2, 0.05),), seed=3) \
        if request.param == "capture" else None
    robot, layout, samples = _samples(request.param, 0.5, faults)
    c = ecore.EstimatorCore(robot, layout=layout)
    rows = ecore.sample_rows(samples, c.joint_index, c.arm_index)
    eff = np.concatenate([c.feed(rows).copy(), c.flush().copy()])
    return robot, c, eff


@pytest.mark.parametrize("form", ["zenoh", "log"])
def test_efforts_as_their_objects_would_be(run, form):
    robot, c, rows = run
    enc = EffortJson(c)
    got = enc.messages(rows)
    objs = c.efforts(rows)
    assert len(got) == len(objs) > 300 and not enc.failed.any()
    assert got == _python(objs, form)
    assert any(o.flags for o in objs) and any(not o.flags for o in objs)
    assert any(getattr(o, "commanded_nm", None) == () for o in objs)


@pytest.mark.parametrize("form", ["zenoh", "log"])
def test_samples_as_their_objects_would_be(run, form):
    robot, _, _ = run
    from gateway.engine.warm import frames
    from drivers.kernel import columns_from_messages

    wm = WireMap.from_robot(robot)
    names = list(wm.buses)
    from simulator import scenario
    from simulator.engine import Simulation

    sim = Simulation(scenario.load("capture" if robot.name == "paper_robot" else "three_arm", {"duration_s": 0.2}))
    fw = firmware.Firmware(sim.robot)
    pairs = []
    while sim.k < sim.n_steps:
        pairs += [(names.index(b), m) for b, m in fw.frames(sim.step())]
    core = DriverCore(wm)
    events = core.feed(columns_from_messages(pairs)).copy()
    enc = SampleJson([a.name for a in robot.arms], robot.joint_names)
    got = enc.messages(events)
    objs = core.to_samples(events)
    assert len(got) == len(objs) > 1000
    assert {type(o).__name__ for o in objs} == {"WrenchSample", "JointSample", "TorqueCommand", "ImuSample",
                                               "ThrusterCommand", "ValveCommand"}
    assert got == _python(objs, form)
    assert frames  # (the warm-up's frames exist too; kept importable)


def test_a_non_finite_value_is_left_to_python(run):
    robot, c, rows = run
    bad = rows[:3].copy()
    bad["full_nm"][1, 0] = np.nan
    enc = EffortJson(c)
    buf, off = enc.encode(bad)
    per = enc.per_row
    assert enc.failed.tolist() == [0] * per + [1] + [0] * (2 * per - 1)
    assert off[per + 1] == off[per]                      # nothing written for it


def _valve_rows(c, k=5, seed=0):
    """``k`` valve rows of core ``c``: its filter now (the prior), with random flags."""
    rows = np.zeros(k, dtype=c.valve_dtype)
    rng = np.random.default_rng(seed)
    for r in range(k):
        c.valve_row(rows, r)
        rows["t_ns"][r] = 1_000_000 * (r + 1)
        rows["flags"][r] = rng.random(len(c.flag_names)) < 0.1 * r
    rows["wrench"] *= rng.uniform(0.5, 2.0, rows["wrench"].shape)     # values of every magnitude
    rows["wrench"][0, 0] = -0.0
    return rows


@pytest.mark.parametrize("form", ["zenoh", "log"])
def test_valve_wrenches_as_their_objects_would_be(run, form):
    from gateway.engine.encode import ValveJson

    robot, c, _ = run
    rows = _valve_rows(c)
    enc = ValveJson(c)
    objs = c.valve_objects(rows)
    assert enc.messages(rows) == _python(objs, form) and not enc.failed.any()
    assert any(o.flags for o in objs) and any(not o.flags for o in objs)


def test_a_non_finite_valve_wrench_is_left_to_python(run):
    from gateway.engine.encode import ValveJson

    robot, c, _ = run
    rows = _valve_rows(c, 3)
    rows["force_sigma_n"][1, 2] = np.inf
    enc = ValveJson(c)
    buf, off = enc.encode(rows)
    assert enc.failed.tolist() == [0, 1, 0] and off[2] == off[1]
