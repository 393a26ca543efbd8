"""The thruster filter's learned per-valve wrenches on ``bsc/<robot>/efforts/valves``: their rate,
their values (the filter's state as of an epoch), and the same bytes however the frames are split."""
from __future__ import annotations

import numpy as np
import pytest

from gateway import codec, keys
from gateway.efforts import ThrusterEffort, ValveWrenches
from gateway.engine import Session, Sink
from gateway.pipeline import VALVE_WRENCH_PERIOD_NS, Pipeline
from simulator import scenario
from simulator.engine import Simulation
from simulator.firmware import Faults, Firmware

DURATION_S = 0.6


def frames(duration_s=DURATION_S, faults=None):
    sc = scenario.load("capture", {"duration_s": duration_s})
    sim = Simulation(sc)
    fw = Firmware(sim.robot, faults=faults)
    out = []
    while sim.k < sim.n_steps:
        out.extend(fw.frames(sim.step()))
    out.extend(fw.flush())
    return sim.robot, out


@pytest.fixture(scope="module")
def run():
    return frames()


class Collect(Sink):
    def __init__(self):
        self.got: list = []

    def emit(self, key, obj, log_ns):
        self.got.append((key, obj, log_ns))


def valve_records(robot, fl, split):
    """(key, payload, log time) of every valve-wrench record and (t_ns, flags) of every thruster
    effort, feeding ``fl`` in batches of ``split`` frames (1: frame by frame, as a live gateway)."""
    sink = Collect()
    ses = Session(robot, [sink])
    if split == 1:
        for bus, msg in fl:
            ses.feed(bus, msg)
    else:
        for k in range(0, len(fl), split):
            ses.feed_messages(fl[k:k + split])
    ses.close()
    valves = [(k, codec.encode(o), t) for k, o, t in sink.got if isinstance(o, ValveWrenches)]
    efforts = {o.t_ns: o for _, o, _ in sink.got if isinstance(o, ThrusterEffort)}
    order = {}
    for k, o, t in sink.got:
        if "/efforts/" in k:
            order.setdefault(k, []).append((o.t_ns, t))      # and its log time: the frame that made it
    return valves, efforts, order


def test_one_record_per_window_with_the_filter_state_and_the_efforts_quality(run):
    robot, fl = run
    sink = Collect()
    ses = Session(robot, [sink])
    checked = seen = 0
    for bus, msg in fl:
        ses.feed(bus, msg)
        now = [o for _, o, _ in sink.got[seen:] if isinstance(o, ValveWrenches)]
        seen = len(sink.got)
        if now:
            # taken after this frame's valve command sample, the last thing fed: the filter as now
            # (it does not move between two epochs' computations)
            W, sigma = ses.pipeline.estimator.valve_wrenches()
            assert now[-1].wrench == tuple(W.ravel().tolist()) and now[-1].force_sigma_n == tuple(sigma.tolist())
            checked += len(now)
    ses.close()
    recs = [o for k, o, _ in sink.got if isinstance(o, ValveWrenches)]
    assert {k for k, o, _ in sink.got if isinstance(o, ValveWrenches)} == {keys.valve_wrenches(robot.name)}
    n = ses.pipeline.estimator.layout.n
    assert all(len(r.wrench) == 6 * n and len(r.force_sigma_n) == n for r in recs)
    # at most one per window, about one per window over the run, each a newer epoch
    t = np.array([r.t_ns for r in recs])
    assert np.all(np.diff(t) > 0)
    windows = DURATION_S * 1e9 / VALVE_WRENCH_PERIOD_NS
    assert windows - 3 <= len(recs) <= windows + 1, len(recs)
    assert checked == len(recs)
    # quality: that of the thruster effort of the same epoch
    efforts = {o.t_ns: o for _, o, _ in sink.got if isinstance(o, ThrusterEffort)}
    assert all(r.t_ns in efforts and (r.good, r.flags) == (efforts[r.t_ns].good, efforts[r.t_ns].flags)
               for r in recs)
    assert sum(r.good for r in recs) > 0.9 * len(recs)
    # the filter learns: the wrenches move off the prior, the valves fired become surer
    assert recs[-1].wrench != recs[0].wrench
    assert min(recs[-1].force_sigma_n) < 0.5 * min(recs[0].force_sigma_n)
    assert codec.decode(codec.encode(recs[-1])) == recs[-1]


@pytest.mark.parametrize("split", [7, 1000, 10 ** 6])
def test_the_same_bytes_however_the_frames_are_split(run, split):
    robot, fl = run
    one, _, order = valve_records(robot, fl, 1)
    other, _, other_order = valve_records(robot, fl, split)
    assert len(one) > 100
    assert [p for _, p, _ in other] == [p for _, p, _ in one]
    assert [t for _, _, t in other] == [t for _, _, t in one]
    # and every effort key the same sequence (within one call the records come before the efforts)
    assert other_order == order


def test_lost_valve_frames_still_give_records_flagged_as_the_efforts(run):
    robot, fl = frames(0.3, Faults(drop_rate=0.05, seed=4, from_s=0.1))
    got, efforts, _ = valve_records(robot, fl, 1)
    recs = [codec.decode(p) for _, p, _ in got]
    assert len(recs) > 15
    assert all((r.good, r.flags) == (efforts[r.t_ns].good, efforts[r.t_ns].flags) for r in recs)


def test_no_estimator_no_records(run):
    robot, fl = run
    got = []
    pl = Pipeline(robot, emit=lambda k, o: got.append(o), estimate=False)
    for bus, msg in fl[:2000]:
        pl.feed(bus, msg)
    assert got and not any(isinstance(o, ValveWrenches) for o in got)
