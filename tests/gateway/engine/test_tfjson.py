"""The /tf messages written by the compiled kernel (gateway.engine.tfjson) are byte for byte the
ones the Python writer makes (gateway.log.foxglove: the message as a dict, the recorder's JSON
encoder): over simulated sessions fed in a replay's batches, over random rows with bad values,
and Python's ``round`` to 9 decimals on every kind of double."""
from __future__ import annotations

import math

import numpy as np
import pytest

import robot_description
from gateway.engine.tfjson import TransformJson, round_digits
from gateway.log.foxglove import DIGITS, FrameTransforms
from gateway.log.schema import encode_json


def _both(robot, batches, names):
    """(the Python writer's bytes, the kernel's) of each batch of (events, log_ns)."""
    py, jit = FrameTransforms(robot), FrameTransforms(robot)
    enc = TransformJson(jit)
    want, got = [], []
    for ev, log in batches:
        want.append([(t, encode_json(m).encode()) for t, m in py.rows(ev, log, names)])
        times, angles, quats, m = jit.snapshots(ev, log, names)
        got.append(list(zip(times[:m].tolist(), enc.messages(times, angles, quats, m))))
        assert jit.angles == py.angles and jit.attitude == py.attitude and jit._next == py._next
    return want, got


@pytest.mark.parametrize("scenario", [None, "three_arm"])
def test_a_simulated_session_in_a_replays_batches(scenario):
    """The default scenario and three spatial arms with an IMU mounted turned by 90 degrees, its
    firmware's frames in 20 ms batches (a replay's chunk) through the drivers."""
    from drivers.kernel import DriverCore, columns_from_messages
    from drivers.wire import WireMap
    from simulator import scenario as scenarios
    from simulator.engine import Simulation
    from simulator.firmware import Firmware

    sim = Simulation(scenarios.load(scenario).replace(duration_s=0.6))
    fw = Firmware(sim.robot)
    wire = WireMap.from_robot(sim.robot)
    drivers = DriverCore(wire)
    index = {b: i for i, b in enumerate(wire.buses)}
    batches, pairs = [], []
    while sim.k < sim.n_steps:
        pairs += [(index[bus], msg) for bus, msg in fw.frames(sim.step())]
        if sim.k % 20 == 0:
            rows = columns_from_messages(pairs)
            ev = drivers.feed(rows).copy()
            batches.append((ev, rows["t_ns"][ev["frame"]] + 1_000_000_000))
            pairs = []
    want, got = _both(sim.robot, batches, drivers.joint_names)
    assert sum(map(len, want)) >= 25 and got == want


def test_random_rows_with_bad_values():
    """No IMU sample at first, joints without an angle yet, NaN angles, zero quaternions,
    unknown joints, several messages in a batch and none."""
    from drivers.kernel import EVENT_DTYPE, IMU, JOINT, WRENCH

    robot = robot_description.load("paper_robot")
    names = ("arm0/j1", "arm0/j2", "arm1/j1", "arm1/j2", "arm9/j1")
    rng = np.random.default_rng(11)
    n = 4000
    ev = np.zeros(n, EVENT_DTYPE)
    ev["kind"] = rng.choice([JOINT, JOINT, IMU, WRENCH], n)
    ev["kind"][:300] = np.where(ev["kind"][:300] == IMU, WRENCH, ev["kind"][:300])
    ev["device"] = np.where(ev["kind"] == JOINT, rng.integers(0, len(names), n), 0)
    ev["values"][:, :4] = rng.normal(size=(n, 4)) * rng.choice([1e-3, 1.0, 30.0], (n, 1))
    ev["values"][rng.random(n) < 0.05, 0] = np.nan
    ev["values"][rng.random(n) < 0.05, :4] = 0.0
    log = 1_000_000_000 + np.cumsum(rng.integers(0, 900_000, n)).astype(np.int64)
    cuts = [0, 40, 41, 300, 1000, 1017, 2500, n]
    want, got = _both(robot, [(ev[a:b], log[a:b]) for a, b in zip(cuts[:-1], cuts[1:])], names)
    assert sum(map(len, want)) > 20 and any(len(w) > 1 for w in want) and got == want
    flat = [data for w in want for _, data in w]
    assert b'"world"' not in flat[0] and b'"world"' in flat[-1]


def test_round_is_pythons():
    rng = np.random.default_rng(5)
    xs = [0.0, -0.0, 1.0, -1.0, 5e-10, -5e-10, 1.5e-9, 2.5e-9, 0.9999999995, 1.0000000000000002, 5e-324]
    xs += [m / 1024 for m in range(-2048, 2049)]                      # exact ties at the 10th decimal
    xs += [m / 2.0 ** k for k in range(10, 40) for m in range(-9, 10)]
    xs += rng.uniform(-1, 1, 20000).tolist() + rng.uniform(-1e-6, 1e-6, 5000).tolist()
    bits = rng.integers(0, 2 ** 63, 50000, dtype=np.int64).view(np.float64)
    xs += [float(b) for b in bits if math.isfinite(b) and abs(b) < 1e6]
    scale = float(10 ** DIGITS)
    assert [repr(round_digits(x, scale)) for x in xs] == [repr(round(x, DIGITS)) for x in xs]


def test_a_value_beyond_the_kernels_rounding_goes_to_python(tmp_path):
    """An axis that is not a unit vector could make a component large: the writer falls back to
    the objects, the same messages."""
    from drivers.kernel import EVENT_DTYPE, JOINT
    from gateway.log import reader
    from gateway.log.foxglove import TF_TOPIC, TransformWriter
    from gateway.log.recorder import Recorder

    robot = robot_description.load("paper_robot")
    names = ("arm0/j1", "arm0/j2", "arm1/j1", "arm1/j2")
    ev = np.zeros(64, EVENT_DTYPE)
    ev["kind"] = JOINT
    ev["device"] = np.arange(64) % 4
    ev["values"][:, 0] = np.linspace(-1, 1, 64)
    log = (np.arange(64) * 5_000_000).astype(np.int64)
    out = []
    for k, encoder in enumerate((None, TransformJson)):
        with Recorder(tmp_path / f"{k}.mcap") as rec:
            tw = TransformWriter(rec, robot, encoder=encoder)
            tw.tf._joints = [j[:4] + ((1e7, 1e7, 1e7),) + j[5:] for j in tw.tf._joints]
            if encoder is not None:
                tw.encoder = TransformJson(tw.tf)         # its axes too: the kernel refuses them
            assert tw.rows(ev, log, names) == (15, 0)
        out.append([m.data for m in reader.read_messages(tmp_path / f"{k}.mcap", [TF_TOPIC])])
    assert out[0] == out[1] and len(out[0]) == 15
