"""The gateway's direct receive mode (one worker thread polls every bus's socket): what SocketCAN
and udp_multicast deployments run. Buses: :mod:`dgram_bus` (real file descriptors, in-process);
the simulator's capture scenario and its firmware make the frames. zenoh: loopback, no scouting."""
from __future__ import annotations

import threading
import time
import uuid

import can
import pytest

from drivers import wire
from drivers.samples import BusHealth, WrenchSample
from gateway import keys
from gateway.bridge import GatewayError, GatewayService, Probe
from gateway.config import GatewayConfig
from gateway.efforts import JointEfforts, ThrusterEffort
from simulator import firmware, scenario
from simulator.engine import DT_S, Simulation

from dgram_bus import dgram_pair
from support import subscribed
from test_bridge import Collector, sessions  # noqa: F401 - the zenoh pair fixture

WAIT_S = 20.0


class Rig:
    """The capture scenario's firmware frames onto one datagram bus pair per robot bus."""

    def __init__(self, seconds: float = 0.4):
        self.sim = Simulation(scenario.load("capture", {"duration_s": seconds}))
        self.robot = self.sim.robot
        self.fw = firmware.Firmware(self.robot)
        self.rx, self.tx = {}, {}
        for name in wire.WireMap.from_robot(self.robot).buses:
            self.rx[name], self.tx[name] = dgram_pair(name)
        self.sent = {name: 0 for name in self.rx}

    def steps(self, n: int, *, realtime: bool = False) -> None:
        """``n`` simulator steps' frames (stamped with simulated time); ``realtime``: step k goes
        out k ms after the first (otherwise as fast as the sockets take them)."""
        t0 = time.monotonic()
        for k in range(n):
            if self.sim.k >= self.sim.n_steps:
                return
            r = self.sim.step()
            if realtime:
                wait = t0 + k * DT_S - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
            for bus, msg in self.fw.frames(r):
                self.tx[bus].send(msg)
                self.sent[bus] += 1

    def close(self) -> None:
        for b in (*self.rx.values(), *self.tx.values()):
            b.shutdown()


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def wait_for(pred, what: str, timeout: float = WAIT_S) -> None:
    end = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < end, what
        time.sleep(0.005)


def test_direct_mode_is_chosen_for_pollable_buses_and_publishes_everything(sessions, rig):  # noqa: F811
    pub_s, sub_s = sessions
    name = rig.robot.name
    seen = {JointEfforts: 0, ThrusterEffort: 0, WrenchSample: 0}

    def everything(got) -> bool:
        """Every epoch's efforts (300 steps: 2 arms + the thrusters each) and a sample arrived.
        The epochs still open when the service closes are published by its final flush, so this
        holds only after close: the count, not a first few, says when the subscriber has it all."""
        t = type(got[-1][1])
        if t in seen:
            seen[t] += 1
        return seen[JointEfforts] >= 2 * 300 and seen[ThrusterEffort] >= 300 and seen[WrenchSample] > 0

    col = Collector(everything)
    sub = sub_s.declare_subscriber(keys.everything(name), col)
    try:
        subscribed(pub_s, keys.everything(name))
        with GatewayService(rig.robot, rig.rx, pub_s) as gw:
            assert gw.receive == "direct" and gw.stats["receive"] == "direct"
            assert gw.thread_ids()["notifiers"] == []         # no notifier thread at all
            rig.steps(300, realtime=True)
            wait_for(lambda: gw.stats["received"] == sum(rig.sent.values()), "frames not all received")
            assert gw.drain(WAIT_S)
            st = gw.stats
            assert st["processed"] == st["received"] == sum(rig.sent.values()) and st["dropped"] == 0
        assert col.done.wait(WAIT_S), seen
        efforts = [o for _, o in col.got if isinstance(o, JointEfforts)]
        assert len(efforts) == 2 * 300 and sum(e.good for e in efforts) >= 0.95 * len(efforts)
    finally:
        sub.undeclare()


def test_direct_mode_samples_go_out_without_an_estimator(sessions, rig):  # noqa: F811
    """Without the estimator nothing is held: the samples are what the gateway publishes."""
    pub_s, sub_s = sessions
    col = Collector(lambda got: sum(isinstance(o, WrenchSample) for _, o in got) >= 20)
    sub = sub_s.declare_subscriber(keys.sensors(rig.robot.name), col)
    try:
        subscribed(pub_s, keys.sensors(rig.robot.name))
        with GatewayService(rig.robot, rig.rx, pub_s, GatewayConfig().updated(service={"estimate": False})):
            rig.steps(20)
            assert col.done.wait(WAIT_S), len(col.got)
    finally:
        sub.undeclare()


QUICK_RETRY = GatewayConfig().updated(service={"retry_s": 0.05})


def receive(mode: str) -> GatewayConfig:
    return GatewayConfig().updated(can={"receive": mode})


def test_receive_modes_are_checked(sessions, rig):  # noqa: F811
    pub_s, _ = sessions
    prefix = f"bsc-direct-{uuid.uuid4().hex}"
    virtual = {n: can.Bus(interface="virtual", channel=wire.channel_name(prefix, n), ignore_config=True)
               for n in rig.rx}
    try:
        with pytest.raises(GatewayError, match="pollable"):
            GatewayService(rig.robot, virtual, pub_s, receive("direct"))
        with pytest.raises(GatewayError, match="receive must be"):
            GatewayService(rig.robot, rig.rx, pub_s, receive("fast"))
        assert GatewayService(rig.robot, virtual, pub_s).receive == "threads"
        gw = GatewayService(rig.robot, rig.rx, pub_s, receive("threads")).start()
        try:
            rig.steps(5)
            wait_for(lambda: gw.stats["received"] == sum(rig.sent.values()), "threads mode over pollable buses")
        finally:
            gw.close()
    finally:
        for b in virtual.values():
            b.shutdown()


@pytest.mark.parametrize("mode", ["direct", "threads"])
def test_a_probe_is_told_every_frame_received_and_fed_and_every_tick(sessions, rig, mode):  # noqa: F811
    """The benchmarks' timing hooks (bridge.Probe): each frame once received, each batch fed once
    after its 'feeding' call, the health ticks; and the thread ids for per-thread CPU."""
    pub_s, _ = sessions
    events: list = []

    class Recorded(Probe):
        def received(self, bus, stamps):
            events.append(("received", bus, list(stamps)))

        def feeding(self, stamps):
            events.append(("feeding", list(stamps)))

        def fed(self, stamps):
            events.append(("fed", list(stamps)))

        def ticked(self, start, end):
            events.append(("tick", start, end))

    cfg = GatewayConfig().updated(can={"receive": mode}, service={"health_period_s": 0.02})
    with GatewayService(rig.robot, rig.rx, pub_s, cfg, probe=Recorded()) as gw:
        tids = gw.thread_ids()
        assert len(tids["worker"]) == 1 and (len(tids["notifiers"]) == len(rig.rx) if mode == "threads"
                                             else tids["notifiers"] == [])
        rig.steps(40)
        sent = sum(rig.sent.values())
        wait_for(lambda: gw.stats["received"] == sent, "frames not all received")
        assert gw.drain(WAIT_S)
        gw.run(duration_s=0.2)
    received = sorted(s for e in events if e[0] == "received" for s in e[2])
    fed = [e for e in events if e[0] in ("feeding", "fed")]
    assert len(received) == sent and sorted(s for e in fed if e[0] == "fed" for s in e[1]) == received
    assert [e[0] for e in fed] == ["feeding", "fed"] * (len(fed) // 2)
    assert all(a[1] == b[1] for a, b in zip(fed[::2], fed[1::2]))
    ticks = [e for e in events if e[0] == "tick"]
    assert len(ticks) >= 2 and all(end >= start for _, start, end in ticks)


def test_direct_mode_a_failing_bus_is_counted_and_the_others_continue(sessions, rig):  # noqa: F811
    pub_s, _ = sessions
    with GatewayService(rig.robot, rig.rx, pub_s, QUICK_RETRY) as gw:
        rig.steps(20)
        wait_for(lambda: gw.stats["received"] == sum(rig.sent.values()), "before the failure")
        rig.rx["arm1"].failing = True
        before = {n: gw.bus_state[n].received for n in rig.rx}
        rig.steps(40, realtime=True)
        wait_for(lambda: gw.bus_state["arm1"].down_since is not None, "the failure is not seen")
        st = gw.bus_state["arm1"]
        assert st.rx_errors >= 1 and st.outages == 1 and "link down" in st.last_error
        for other in ("arm0", "spacecraft"):          # unaffected
            wait_for(lambda: gw.bus_state[other].received == rig.sent[other], f"{other} stalled")
        assert gw.bus_state["arm1"].received == before["arm1"]
        rig.rx["arm1"].failing = False                # back: what waited in its socket comes in
        rig.steps(10)
        wait_for(lambda: gw.bus_state["arm1"].received == rig.sent["arm1"], "arm1 did not resume")
        wait_for(lambda: st.down_since is None, "arm1 still down")
        assert st.outages == 1
        health = {h.bus: h for h in gw.health() if isinstance(h, BusHealth)}
        assert dict(health["arm1"].rejected).get("rx_error", 0) == st.rx_errors


def test_direct_mode_a_bus_gone_under_the_gateway_is_reopened(sessions, rig):  # noqa: F811
    pub_s, _ = sessions
    spare: dict = {}
    lock = threading.Lock()

    def reopen(name: str):
        with lock:
            if name in spare:
                raise can.CanInitializationError("only one spare")
            spare[name] = dgram_pair(f"{name}-new")
            return spare[name][0]

    try:
        with GatewayService(rig.robot, rig.rx, pub_s, QUICK_RETRY, reopen=reopen) as gw:
            rig.steps(20)
            wait_for(lambda: gw.stats["received"] == sum(rig.sent.values()), "before")
            rig.rx["arm0"].break_socket()             # the adapter went away
            st = gw.bus_state["arm0"]
            # the new bus is in place before its counters are (replace_bus): wait for both
            wait_for(lambda: "arm0" in spare and gw.buses["arm0"] is spare["arm0"][0] and st.reopened == 1,
                     "no reopen")
            assert st.outages == 1 and st.rx_errors >= 1 and st.reopened == 1
            got = st.received
            rig.tx.pop("arm0").shutdown()
            rig.tx["arm0"] = spare["arm0"][1]             # the firmware now reaches the new bus
            rig.sent["arm0"] = 0
            rig.steps(10)
            wait_for(lambda: st.received == got + rig.sent["arm0"], "nothing from the new bus")
            wait_for(lambda: st.down_since is None, "still down")
        assert getattr(spare["arm0"][0], "_is_shutdown", False)     # the service closed what it opened
    finally:
        for rx, _ in spare.values():
            rx.shutdown()                 # (its tx is in the rig now)


def test_direct_mode_overflow_is_counted_frame_by_frame(sessions, rig):  # noqa: F811
    pub_s, _ = sessions
    gw = GatewayService(rig.robot, rig.rx, pub_s, GatewayConfig().updated(service={"max_backlog": 40}))
    feed = gw.engine.feed_frames

    def slow_feed(rows, log_ns=None):             # a worker far slower than the buses
        time.sleep(0.0005 * len(rows))
        feed(rows, log_ns)

    gw.engine.feed_frames = slow_feed
    try:
        gw.start()
        rig.steps(150)
        wait_for(lambda: gw.stats["received"] == sum(rig.sent.values()), "frames not all received")
        assert gw.drain(WAIT_S)
        st = gw.stats
        assert st["dropped"] > 0 and st["overflow_episodes"] >= 1 and st["peak_backlog"] == 40
        assert st["received"] == st["processed"] + st["dropped"] == sum(rig.sent.values())
        health = {h.bus: dict(h.rejected) for h in gw.health() if isinstance(h, BusHealth)}
        assert sum(r.get("overflow", 0) for r in health.values()) == st["dropped"]
    finally:
        gw.close()


def test_direct_mode_a_backlog_is_taken_in_time_order_across_buses(sessions, rig):  # noqa: F811
    """Buses carry different frame rates (arm ~4.5, spacecraft ~4.3 frames per step): a worker
    that is behind must still feed the pipeline in time order, not the same number of frames
    from each bus in turn (which lets the busier bus fall behind until its epochs are forced
    out). A slowed pipeline makes the backlog; every frame must go in in timestamp order."""
    pub_s, _ = sessions
    gw = GatewayService(rig.robot, rig.rx, pub_s)
    feed = gw.engine.feed_frames
    fed = []

    def slow_feed(rows, log_ns=None):
        fed.extend(rows["t_ns"].tolist())
        time.sleep(0.0001 * len(rows))
        feed(rows, log_ns)

    gw.engine.feed_frames = slow_feed
    try:
        gw.start()
        sender = threading.Thread(target=rig.steps, args=(300,))
        sender.start()
        sender.join(WAIT_S)
        wait_for(lambda: gw.stats["received"] == sum(rig.sent.values()), "frames not all received")
        assert gw.drain(WAIT_S)
        assert gw.stats["peak_backlog"] > 100                     # it was behind
        assert len(fed) == sum(rig.sent.values()) and fed == sorted(fed)
        est = gw.engine.pipeline.estimator
        assert est.late == 0 and est.epochs == 300 and est.good >= 295
    finally:
        gw.close()


def test_merged_backlog_waits_for_a_bus_that_may_hold_earlier_frames():
    import numpy as np

    from drivers.kernel import FRAME_DTYPE
    from gateway.bridge import _RowBacklog

    def rows(*ts):
        r = np.zeros(len(ts), dtype=FRAME_DTYPE)
        r["t_ns"] = ts
        return r

    b = _RowBacklog(["a", "b"])
    b.append("a", rows(2, 3))
    b.unread["b"] = True                      # b's socket may hold frames earlier than 2
    assert len(b) == 2 and len(b.take(10)) == 0
    assert b.take(1, all_read=True)["t_ns"].tolist() == [2]
    b.unread["b"] = False
    b.append("b", rows(1))
    assert b.take(10)["t_ns"].tolist() == [1, 3] and len(b) == 0 and len(b.take(10)) == 0
    # FIFO within a bus even when its stamps go back (a reordered frame); ties: the lower bus
    b.append("a", rows(5, 4, 9))
    b.append("b", rows(5, 6))
    assert b.take(3)["t_ns"].tolist() == [5, 4, 5] and b.waiting("a") == 1 and b.waiting("b") == 1
    for k in range(1000):                     # compaction and growth keep the order
        b.append("b", rows(10 + k))
    assert b.take(2000)["t_ns"].tolist() == [6, 9] + list(range(10, 1010))


def test_direct_mode_recording_replays_to_the_same_efforts(sessions, rig, tmp_path):  # noqa: F811
    """What a direct-mode gateway records, replayed offline, gives byte-identical efforts: the
    recorder keeps the frames in the order the worker fed them, across buses (a batch merged by
    time from several buses must not be written bus by bus). And what it published on zenoh is
    what it recorded, byte for byte: one JSON form for a sample, on the wire and in the log."""
    from gateway.log.recorder import Recorder
    from gateway.log.context import session_context
    from gateway.log.reader import iter_file_order
    from gateway.replay import OUTPUT_NAME, replay_offline

    pub_s, sub_s = sessions
    path = tmp_path / "live.mcap"
    published: list = []

    def efforts(p):
        return [(t, m.log_time, bytes(m.data)) for t, _, m in iter_file_order(p, lambda t, s: "/efforts/" in t)]

    sub = sub_s.declare_subscriber(keys.efforts(rig.robot.name),
                                   lambda s: published.append((str(s.key_expr), s.payload.to_bytes())))
    try:
        subscribed(pub_s, keys.efforts(rig.robot.name))
        with Recorder(path) as rec:
            rec.add_session_context(**session_context(rig.robot))
            with GatewayService(rig.robot, rig.rx, pub_s, record=rec) as gw:
                assert gw.receive == "direct"
                rig.steps(300)                                   # as fast as the sockets take them
                wait_for(lambda: gw.stats["received"] == sum(rig.sent.values()), "frames not all received")
                assert gw.drain(WAIT_S)
        live = efforts(path)
        wait_for(lambda: len(published) >= len(live), "efforts not all published")
    finally:
        sub.undeclare()
    report = replay_offline(path, tmp_path / "out")
    # every epoch's joint and thruster efforts, and the learned per-valve wrenches (one per 5 ms)
    valves = [m for t, _, m in live if t == keys.valve_wrenches(rig.robot.name)]
    assert len(live) - len(valves) == 3 * 300 and 45 <= len(valves) <= 60
    assert report.frames_in == sum(rig.sent.values())
    replayed = efforts(tmp_path / "out" / OUTPUT_NAME)
    # key by key the same messages at the same log times (across keys, a call's valve wrenches
    # come before its efforts: their place among them depends on how the frames were batched)
    assert sorted(replayed) == sorted(live) and [m for t, _, m in replayed if t == keys.valve_wrenches(
        rig.robot.name)] == valves
    for key in {t for t, _, _ in live}:
        assert [x for x in replayed if x[0] == key] == [x for x in live if x[0] == key]
    assert sorted(published) == sorted((t, m) for t, _, m in live)    # topic = key; the same bytes


def test_payloads_declare_their_encoding_and_their_schemas_are_queryable(sessions, rig):  # noqa: F811
    """A client that knows nothing of bsc finds every payload type's JSON schema on zenoh
    (bsc/<robot>/schemas/<Type>, application/schema+json), and what the gateway publishes is
    application/json that validates against the schema its "type" names."""
    import json

    import jsonschema

    from gateway import codec

    pub_s, sub_s = sessions
    name = rig.robot.name
    got = []
    done = threading.Event()

    def on_sample(s):
        got.append((str(s.encoding), json.loads(s.payload.to_bytes())))
        if {p["type"] for _, p in got} >= {"JointEfforts", "ThrusterEffort", "WrenchSample", "BusHealth"}:
            done.set()

    sub = sub_s.declare_subscriber(keys.everything(name), on_sample)
    try:
        subscribed(pub_s, keys.everything(name))
        with GatewayService(rig.robot, rig.rx, pub_s) as gw:
            schemas, end = {}, time.monotonic() + WAIT_S
            while set(schemas) != set(codec.TYPES) and time.monotonic() < end:
                schemas = codec.fetch_schemas(sub_s, name, timeout_s=1.0)   # the declaration may still travel
            assert set(schemas) == set(codec.TYPES)
            one = list(sub_s.get(keys.schema(name, "JointEfforts"), timeout=5.0))
            assert len(one) == 1 and str(one[0].ok.encoding).startswith("application/schema+json")
            rig.steps(60)
            wait_for(lambda: gw.stats["received"] == sum(rig.sent.values()), "frames not all received")
            assert gw.drain(WAIT_S)
            gw.publish_health()
            assert done.wait(WAIT_S), {p["type"] for _, p in got}
    finally:
        sub.undeclare()
    for encoding, payload in got:
        assert encoding.startswith("application/json"), encoding
        jsonschema.Draft202012Validator(schemas[payload["type"]]).validate(payload)
    bad = dict(got[0][1], t_ns="soon")
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.Draft202012Validator(schemas[bad["type"]]).validate(bad)


def test_direct_mode_reads_a_bus_that_received_after_the_poll_before_merging(sessions):  # noqa: F811
    """The race behind an out-of-order feed: the worker polls, reads the bus that was ready, and
    meanwhile an earlier frame reaches another bus (here: reading the spacecraft bus makes it
    arrive on arm0). Merging right away fed the later frame first; the worker now reads every bus
    with nothing queued before it merges, so the earlier frame goes in first."""
    import socket

    from dgram_bus import DgramBus

    robot = robot_description_load()
    names = list(wire.WireMap.from_robot(robot).buses)
    rx, tx = {}, {}
    for n in names:
        rx[n], tx[n] = dgram_pair(n)

    class ArrivesWhileRead(DgramBus):
        fired = False

        def _recv_internal(self, timeout):
            msg, filtered = super()._recv_internal(timeout)
            if msg is not None and not ArrivesWhileRead.fired:
                ArrivesWhileRead.fired = True
                tx["arm0"].send(can.Message(timestamp=0.0005, arbitration_id=0x7A0, data=bytes(8)))  # earlier
            return msg, filtered

    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
    rx["spacecraft"].shutdown()
    tx["spacecraft"].shutdown()
    rx["spacecraft"], tx["spacecraft"] = ArrivesWhileRead(a, "spacecraft-rx"), DgramBus(b, "spacecraft-tx")
    pub_s, _ = sessions
    gw = GatewayService(robot, rx, pub_s)
    feed, fed = gw.engine.feed_frames, []

    def recording_feed(rows, log_ns=None):
        fed.extend(rows["t_ns"].tolist())
        feed(rows, log_ns)

    gw.engine.feed_frames = recording_feed
    try:
        with gw:
            assert gw.receive == "direct"
            tx["arm1"].send(can.Message(timestamp=0.0, arbitration_id=0x7A2, data=bytes(8)))
            wait_for(lambda: len(fed) == 1, "the first frame fed: the worker is in its polling loop")
            tx["spacecraft"].send(can.Message(timestamp=0.001, arbitration_id=0x7A1, data=bytes(8)))
            wait_for(lambda: len(fed) == 3, f"every frame fed (fed: {fed})")
        assert ArrivesWhileRead.fired and fed == [0, 500_000, 1_000_000]
    finally:
        for bus in (*rx.values(), *tx.values()):
            bus.shutdown()


def robot_description_load():
    import robot_description

    return robot_description.load("paper_robot")


def test_health_before_the_first_frame_is_logged_at_the_time_it_was_taken(sessions, rig, tmp_path):  # noqa: F811
    """A gateway waiting for its buses publishes health every period; recorded, those snapshots
    carry the time they were taken, not log time 0 (a 60 s live recording started in 1970 with
    84 of them); after the first frame, health carries the frames' log time."""
    from gateway.log.recorder import Recorder
    from gateway.log.reader import iter_file_order

    pub_s, _ = sessions
    path = tmp_path / "h.mcap"
    before = time.time_ns()
    with Recorder(path) as rec, GatewayService(rig.robot, rig.rx, pub_s, record=rec) as gw:
        gw.publish_health()
        after = time.time_ns()
        rig.steps(20)
        wait_for(lambda: gw.stats["received"] == sum(rig.sent.values()), "frames not all received")
        assert gw.drain(WAIT_S)
        gw.publish_health()
    times = [m.log_time for t, _, m in iter_file_order(path, lambda t, s: "/health/" in t)]
    first = [t for t in times if t >= before]
    assert len(first) >= 10 and all(before <= t <= after for t in first)
    assert min(times) < 10**9 and max(times) <= after          # then the frames' (simulated) time
