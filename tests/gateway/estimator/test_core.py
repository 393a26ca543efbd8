"""The compiled estimator (gateway.estimator.core) against its oracle, the first wave's Python
estimator (reference_live.py, on Pinocchio and numpy) on the same decoded samples: the same epochs,
times, flags and commanded values exactly; torques and wrenches within 1e-9 of their scale.
And the point of compiling it: the same bits whatever the samples per call."""
from __future__ import annotations

import math

import numpy as np
import pytest

import robot_description
from gateway.efforts import JointEfforts, ThrusterEffort
from gateway.estimator import core
from gateway.estimator import fdi as fd
from gateway.pipeline import Pipeline
from robot_description.thrusters import ThrusterLayout
from simulator import firmware, scenario
from simulator.engine import Simulation

from reference_live import LiveEstimator

REL = 1e-9


def _samples(name: str, duration_s: float, faults: firmware.Faults | None = None):
    """The capture scenario's decoded samples (the drivers' output, arrival order) and its layout."""
    sc = scenario.load(name, {"duration_s": duration_s})
    sim = Simulation(sc)
    fw = firmware.Firmware(sim.robot, faults=faults)
    got: list = []
    pipe = Pipeline(sim.robot, emit=lambda key, obj: got.append(obj), estimate=False)
    while sim.k < sim.n_steps:
        for bus, msg in fw.frames(sim.step()):
            pipe.feed(bus, msg)
    for bus, msg in fw.flush():
        pipe.feed(bus, msg)
    return sim.robot, ThrusterLayout.from_config(sc.cfg.thrusters), got


def _python_efforts(robot, layout, samples) -> list:
    out: list = []
    est = LiveEstimator(robot, out.append, layout=layout)
    for s in samples:
        est.add(s)
    est.flush()
    return out


# The oracle has no thruster fault detector. The compiled core's changes the filter only when it
# suspects a fault (never in these healthy sessions) or holds a valve whose loss CUSUM passed
# hold_valve (it does, early in them: the wrench is then up to 3e-7 of its scale off the oracle);
# compared with the hold off. test_fdi.py checks the hold against the textbook update.
ORACLE = core.CoreSettings(fdi=fd.FdiSettings(hold_valve=0.0))


def _rows_in_chunks(robot, layout, samples, chunks, settings=None) -> tuple[np.ndarray, core.EstimatorCore]:
    c = core.EstimatorCore(robot, layout=layout, settings=settings)
    rows = core.sample_rows(samples, c.joint_index, c.arm_index)
    parts, k = [], 0
    for n in chunks:
        parts.append(c.feed(rows[k:k + n]).copy())
        k += n
    if k < len(rows):
        parts.append(c.feed(rows[k:]).copy())
    parts.append(c.flush().copy())
    return np.concatenate(parts), c


def _close(a, b, what, rel: float = REL) -> None:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    scale = max(1.0, float(np.max(np.abs(b), initial=0.0)))
    assert np.all(np.abs(a - b) <= rel * scale), (what, a, b)


def _compare(new: list, old: list, scales: dict) -> None:
    assert len(new) == len(old)
    for x, y in zip(new, old):
        assert type(x) is type(y)
        assert (x.t_ns, x.good, x.flags) == (y.t_ns, y.good, y.flags), (x, y)
        if isinstance(x, JointEfforts):
            assert (x.arm, x.joints, x.commanded_nm, x.commanded_t_ns, x.rate_rad_s) == \
                (y.arm, y.joints, y.commanded_nm, y.commanded_t_ns, y.rate_rad_s)
            # the full torques take the filter's bias off the measured wrench and weigh the sides
            # by its covariance: rounding amplified there (test_joint_filter.py) reaches them
            _close(x.full_nm, y.full_nm, "full", 1e-8)
            assert x.contact == y.contact == (), (x.contact, y.contact)   # the oracle has no contact test
            _close(x.simplified_nm, y.simplified_nm, "simplified")
            assert len(x.ft_bias) == len(y.ft_bias) and len(x.ft_bias) in (0, 6), (x.ft_bias, y.ft_bias)
            if x.ft_bias:             # the joint filter's state: rounding amplified (test_joint_filter.py)
                _close(x.ft_bias, y.ft_bias, "ft_bias", 1e-7)
        else:
            assert (x.commanded_force_n, x.commanded_moment_nm, x.commanded_t_ns, x.valves) == \
                (y.commanded_force_n, y.commanded_moment_nm, y.commanded_t_ns, y.valves)
            _close(np.array(x.force_n) / scales["force"], np.array(y.force_n) / scales["force"], "force")
            _close(np.array(x.moment_nm) / scales["moment"], np.array(y.moment_nm) / scales["moment"], "moment")


def _scales(old: list) -> dict:
    thr = [e for e in old if isinstance(e, ThrusterEffort)]
    return {"force": max(1.0, max(max(map(abs, e.force_n)) for e in thr)),
            "moment": max(1.0, max(max(map(abs, e.moment_nm)) for e in thr))}


@pytest.fixture(scope="module")
def capture():
    return _samples("capture", 1.5)


def test_same_efforts_as_the_python_estimator(capture):
    robot, layout, samples = capture
    old = _python_efforts(robot, layout, samples)
    rows, c = _rows_in_chunks(robot, layout, samples, [len(samples)], ORACLE)
    new = c.efforts(rows)
    _compare(new, old, _scales(old))
    assert c.epochs == 1500 and c.good > 1400 and c.late == 0


def test_same_efforts_with_faults():
    faults = firmware.Faults(drop_rate=0.02, duplicate_rate=0.02, reorder_rate=0.02, bad_dlc_rate=0.01, seed=5,
                             silent=(("arm1", 0.5, 0.12), ("imu", 0.8, 0.05), ("arm0/j2", 1.0, 0.03)))
    robot, layout, samples = _samples("capture", 1.5, faults)
    old = _python_efforts(robot, layout, samples)
    rows, c = _rows_in_chunks(robot, layout, samples, [len(samples)], ORACLE)
    new = c.efforts(rows)
    _compare(new, old, _scales(old))
    flags = {f for e in new for f in e.flags}
    assert {"missing:arm1", "stale:imu", "stale:arm0/j2"} <= flags, flags


def test_three_arm_robot():
    robot, layout, samples = _samples("three_arm", 0.6)
    old = _python_efforts(robot, layout, samples)
    rows, c = _rows_in_chunks(robot, layout, samples, [len(samples)], ORACLE)
    _compare(c.efforts(rows), old, _scales(old))


def test_same_bits_whatever_the_samples_per_call(capture):
    robot, layout, samples = capture
    whole, _ = _rows_in_chunks(robot, layout, samples, [len(samples)])
    singles, _ = _rows_in_chunks(robot, layout, samples, [1] * len(samples))
    rng = np.random.default_rng(3)
    random, _ = _rows_in_chunks(robot, layout, samples, rng.integers(1, 40, size=len(samples)).tolist())
    for rows in (whole, singles, random):
        rows["cause"] = 0                  # the input row of its call that computed it: call-relative
    assert whole.tobytes() == singles.tobytes() == random.tobytes()


def test_flags_are_named_and_sorted(capture):
    robot, layout, samples = capture
    rows, c = _rows_in_chunks(robot, layout, samples, [len(samples)])
    first = c.efforts(rows[:1])
    assert all(e.flags == tuple(sorted(e.flags)) and "warmup" in e.flags for e in first)
    assert len(c.flag_names) == 5 + 3 * 2 + 4 * 4 + 1 and len(set(c.flag_names)) == len(c.flag_names)
    assert c.flag_names[-1] == "fault:thrusters"


def test_no_samples_no_efforts():
    c = core.EstimatorCore(robot_description.load("paper_robot"))
    assert len(c.feed(np.zeros(0, dtype=core.SAMPLE_DTYPE))) == 0
    assert len(c.flush()) == 0 and c.epochs == 0 and not math.isnan(c.period_ns)


def test_valve_wrenches_are_the_filter_state_with_numpys_bits():
    """The learned valve wrenches (published): W as the filter holds it and each valve's force
    sigma the root of its force covariance's trace, summed in index order, which is the bits the
    numpy form (diag, sum over the three, sqrt) gave; checked on covariances of every scale."""
    c = core.EstimatorCore(robot_description.load("paper_robot"))
    n = c.kf.n
    rng = np.random.default_rng(7)
    differ = 0
    for _ in range(50):
        c.kf.P[...] = rng.random(c.kf.P.shape) * 10.0 ** rng.uniform(-8, 4, c.kf.P.shape)
        c.kf.x[:6 * n] = rng.normal(size=6 * n)
        W, sigma = c.valve_wrenches()
        d = np.diag(c.kf.P)[:6 * n].reshape(n, 6)[:, :3]
        assert W.tobytes() == c.kf.W.tobytes()
        assert sigma.tobytes() == np.sqrt(d.sum(axis=1)).tobytes()
        differ += int(((d[:, 0] + d[:, 1]) + d[:, 2] != d[:, 0] + (d[:, 1] + d[:, 2])).sum())
    assert differ > 50                     # the order of the sum shows in the bits: it is tested


def test_good_efforts_counts_what_is_published_good(capture):
    """The report's count of good efforts is the number of published objects with good=True."""
    robot, layout, samples = capture
    rows, c = _rows_in_chunks(robot, layout, samples, [len(samples)])
    objs = c.efforts(rows)
    good = sum(o.good for o in objs)
    assert 0 < good < len(objs)              # warm-up and flagged epochs are not good
    assert c.good_efforts(rows) == good
    for lo in range(0, len(rows), 37):       # and any part of them
        assert c.good_efforts(rows[lo:lo + 37]) == sum(o.good for o in c.efforts(rows[lo:lo + 37]))
