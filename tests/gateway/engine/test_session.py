"""The session engine: log times, the health cadence, the end of input, and the same output
whatever the sinks want (objects or rows) and however frames are fed (one by one or as rows)."""
from __future__ import annotations

import numpy as np
import pytest

import robot_description
from drivers.kernel import columns_from_messages
from drivers.samples import BusHealth, DeviceHealth
from gateway.efforts import JointEfforts, ThrusterEffort, ValveWrenches
from gateway.engine import Session, Sink
from gateway.engine.warm import frames as synthetic_frames


class Objects(Sink):
    def __init__(self):
        self.got, self.raw = [], []

    def frame(self, bus, msg, log_ns):
        self.raw.append((bus, log_ns))

    def emit(self, key, obj, log_ns):
        self.got.append((key, obj, log_ns))


class Rows(Sink):
    rows = True

    def __init__(self):
        self.efforts, self.samples, self.health = [], [], []

    def sample_rows(self, session, events, log_ns):
        self.samples.append((events.copy(), log_ns.copy()))

    def effort_rows(self, session, rows, log_ns):
        self.efforts.append((rows.copy(), log_ns.copy()))

    def emit(self, key, obj, log_ns):
        self.health.append(obj)


@pytest.fixture(scope="module")
def robot():
    return robot_description.load("paper_robot")


@pytest.fixture(scope="module")
def frames():
    return synthetic_frames(300)


def _run(robot, frames, sinks, **kw):
    with Session(robot, sinks, **kw) as ses:
        for bus, msg in frames:
            ses.feed(bus, msg)
    return ses


def test_log_times_are_frame_times_plus_the_offset(robot, frames):
    out = Objects()
    ses = _run(robot, frames, [out], log_offset_ns=5_000_000_000)
    assert len(out.raw) == len(frames)
    assert [t for _, t in out.raw] == [round(m.timestamp * 1e9) + 5_000_000_000 for _, m in frames]
    efforts = [(obj, t) for _, obj, t in out.got if isinstance(obj, (JointEfforts, ThrusterEffort))]
    assert len(efforts) == 3 * ses.stats["epochs"] and ses.stats["epochs"] == 300
    # an epoch's efforts carry the time of the frame that completed it: at or after the epoch
    assert all(0 <= t - 5_000_000_000 - obj.t_ns < 2_000_000 for obj, t in efforts[-300:])


def test_health_every_period_of_frame_time_and_once_at_the_end(robot, frames):
    out = Objects()
    ses = _run(robot, frames, [out], health_period_ns=100_000_000)
    health = [(obj, t) for _, obj, t in out.got if isinstance(obj, (BusHealth, DeviceHealth))]
    per_snapshot = len(ses.buses) + len(ses.pipeline.drivers.device_names)
    times = sorted({obj.t_ns for obj, _ in health})
    assert times == [100_000_000, 200_000_000, 299_000_000]          # crossings, then the last frame
    assert len(health) == 3 * per_snapshot
    assert ses.close() == [] and len(out.got) == len(out.got)        # closing twice adds nothing


def test_row_and_object_sinks_see_the_same_efforts(robot, frames):
    objs, rows = Objects(), Rows()
    ses = _run(robot, frames, [objs, rows])
    got_rows = np.concatenate([r for r, _ in rows.efforts])
    row_log = np.concatenate([t for _, t in rows.efforts])
    assert len(got_rows) == ses.stats["epochs"] == 300
    efforts = [(obj, t) for _, obj, t in objs.got if isinstance(obj, (JointEfforts, ThrusterEffort))]
    assert efforts and [o for o, _ in efforts] == ses.pipeline.estimator.efforts(got_rows)
    assert [t for _, t in efforts] == np.repeat(row_log, 3).tolist()
    events = np.concatenate([e for e, _ in rows.samples])
    samples = [obj for _, obj, _ in objs.got if not isinstance(obj, (JointEfforts, ThrusterEffort, ValveWrenches,
                                                                       BusHealth, DeviceHealth))]
    assert samples == ses.pipeline.drivers.to_samples(events)
    # objects to both: health, and the learned valve wrenches (no rows of their own)
    health = [h for h in rows.health if isinstance(h, (BusHealth, DeviceHealth))]
    valves = [v for v in rows.health if isinstance(v, ValveWrenches)]
    assert health and valves and len(health) + len(valves) == len(rows.health)
    assert valves == [o for _, o, _ in objs.got if isinstance(o, ValveWrenches)]


def test_frames_as_rows_give_what_frames_one_by_one_give(robot, frames):
    one = Objects()
    _run(robot, frames, [one])
    batch = Objects()
    names = [a.name for a in robot.arms] + ["spacecraft"]
    cols = columns_from_messages([(names.index(b), m) for b, m in frames])
    with Session(robot, [batch]) as ses:
        for lo in range(0, len(cols), 97):                   # any split
            ses.feed_frames(cols[lo:lo + 97])
    # within one call samples come first, then the efforts they completed: the same sequences of
    # efforts, of learned valve wrenches and of samples
    def split(got):
        eff = [(k, o) for k, o, _ in got if isinstance(o, (JointEfforts, ThrusterEffort))]
        valves = [(k, o) for k, o, _ in got if isinstance(o, ValveWrenches)]
        return eff, valves, [(k, o) for k, o, _ in got if not isinstance(o, (JointEfforts, ThrusterEffort,
                                                                             ValveWrenches))]

    assert split(batch.got) == split(one.got) and len(split(one.got)[0]) == 900
    assert len(split(one.got)[1]) >= 50


def test_recorder_sink_writes_rows_in_the_order_they_were_fed(robot, frames, tmp_path):
    """A replay feeds a log's frames in file order, so frames fed as rows (a batch merged by time
    across buses) are written in that order, not bus by bus."""
    from gateway.engine.sinks import RecorderSink
    from gateway.log.recorder import Recorder
    from gateway.log.reader import iter_can_frames

    pairs = frames[:200]
    with Session(robot) as probe:
        buses = list(probe.buses)
    rows = columns_from_messages([(buses.index(b), m) for b, m in pairs])
    rows["t_ns"] = [round(m.timestamp * 1e9) for _, m in pairs]
    assert len(set(rows["bus"][:20].tolist())) > 1            # interleaved buses within one batch
    path = tmp_path / "rows.mcap"
    with Recorder(path) as rec:
        with Session(robot, [RecorderSink(rec, rows=True, offline=True)]) as ses:
            ses.feed_frames(rows[:150])
            ses.feed_frames(rows[150:])
    got = [(b, round(m.timestamp * 1e9), m.arbitration_id) for b, _, m in iter_can_frames(path)]
    assert got == [(b, round(m.timestamp * 1e9), m.arbitration_id) for b, m in pairs]


class ValveRows(Rows):
    """A row sink that takes the learned valve wrenches as rows too (as the recorder's sink does)."""

    def __init__(self):
        super().__init__()
        self.valves = []

    def valve_rows(self, session, rows, log_ns):
        self.valves.append((rows.copy(), log_ns.copy(), [d for _, _, d, _ in session.valve_messages(rows)]))


@pytest.mark.parametrize("form", ["zenoh", "log"])
def test_valve_rows_to_the_sinks_that_take_them_the_objects_bytes(robot, frames, form):
    from gateway import codec
    from gateway.log.schema import dataclass_json

    objs, rows = Objects(), ValveRows()
    ses = _run(robot, frames, [objs, rows])
    valves = [(o, t) for _, o, t in objs.got if isinstance(o, ValveWrenches)]
    assert len(valves) >= 50
    assert not [v for v in rows.health if isinstance(v, ValveWrenches)]     # rows, not objects as well
    got = np.concatenate([r for r, _, _ in rows.valves])
    assert ses.pipeline.estimator.valve_objects(got) == [o for o, _ in valves]
    assert np.concatenate([t for _, t, _ in rows.valves]).tolist() == [t for _, t in valves]
    python = [codec.encode(o) if form == "zenoh" else dataclass_json(ValveWrenches)(o).encode() for o, _ in valves]
    assert [d for _, _, ds in rows.valves for d in ds] == python
