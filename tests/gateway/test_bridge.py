"""The gateway service over virtual CAN and loopback zenoh, and ``bsc gateway`` as a subprocess.

zenoh: explicit loopback endpoints, multicast scouting off (gateway.zenoh_config)."""
from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import can
import pytest
import zenoh

import robot_description
from drivers import frames, wire
from drivers.samples import BusHealth, DeviceHealth, ImuSample, JointSample, WrenchSample
from gateway.efforts import JointEfforts
from gateway import codec, keys
from gateway.bridge import GatewayService
from gateway.config import GatewayConfig
from gateway.zenoh_config import make_config
from support import free_port, subscribed

ROOT = Path(__file__).resolve().parents[2]


class Collector:
    def __init__(self, want):
        self.want, self.got, self.lock, self.done = want, [], threading.Lock(), threading.Event()

    def __call__(self, sample):
        obj = codec.decode(sample.payload.to_bytes())
        with self.lock:
            self.got.append((str(sample.key_expr), obj))
            if self.want(self.got):
                self.done.set()


@pytest.fixture
def sessions():
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    with zenoh.open(make_config(listen=[ep])) as pub, zenoh.open(make_config(connect=[ep])) as sub:
        yield pub, sub


def test_bridge_publishes_samples_and_health(sessions):
    pub_s, sub_s = sessions
    wm = wire.WireMap.from_robot(robot_description.load("paper_robot"))
    prefix = f"bsc-bridge-{uuid.uuid4().hex}"
    arm = wm.buses["arm0"]
    j0 = f"arm0/{arm.joints[0]}"

    def want(got):
        ks = [k for k, _ in got]
        return (keys.wrench("paper_robot", "arm0") in ks and keys.imu("paper_robot") in ks
                and keys.joint("paper_robot", j0) in ks
                and any(k.startswith("bsc/paper_robot/health/bus/") for k in ks))

    col = Collector(want)
    sub = sub_s.declare_subscriber(keys.everything("paper_robot"), col)
    opened = {}
    try:
        for name in wm.buses:
            opened[name] = can.Bus(interface="virtual", channel=wire.channel_name(prefix, name),
                                   receive_own_messages=False, ignore_config=True)
        tx = {name: can.Bus(interface="virtual", channel=wire.channel_name(prefix, name),
                            receive_own_messages=False, ignore_config=True) for name in wm.buses}
        try:
            with GatewayService(wm, opened, pub_s, GatewayConfig().updated(service={"health_period_s": 0.05})) as gw:
                stop = threading.Event()
                runner = threading.Thread(target=gw.run, args=(stop,))
                runner.start()
                try:
                    for c in range(200):
                        for m in frames.encode_wrench(WrenchSample("arm0", 0, c, (1.0, 2.0, 3.0), (0.1, 0.2, 0.3))):
                            tx["arm0"].send(m)
                        tx["arm0"].send(frames.encode_joint(JointSample(j0, 0, c, 0.5, 0.0), 0))
                        for m in frames.encode_imu(ImuSample(0, c, (1.0, 0.0, 0.0, 0.0), (0.0,) * 3, (0.0, 0.0, 0.01))):
                            tx["spacecraft"].send(m)
                        if col.done.wait(0.02):
                            break
                    assert col.done.wait(10.0), [k for k, _ in col.got][:20]
                finally:
                    stop.set()
                    runner.join(10.0)
        finally:
            for b in tx.values():
                b.shutdown()
    finally:
        for b in opened.values():
            b.shutdown()
        sub.undeclare()
    by_key = {}
    for k, obj in col.got:
        by_key.setdefault(k, []).append(obj)
    w = by_key[keys.wrench("paper_robot", "arm0")][0]
    assert isinstance(w, WrenchSample) and w.force_n == (1.0, 2.0, 3.0)
    assert isinstance(by_key[keys.imu("paper_robot")][0], ImuSample)
    healths = [o for k, objs in by_key.items() if "/health/" in k for o in objs]
    assert any(isinstance(h, BusHealth) for h in healths) and any(isinstance(h, DeviceHealth) for h in healths)


def test_service_requires_every_bus_and_closes_twice(sessions):
    wm = wire.WireMap.from_robot(robot_description.load("paper_robot"))
    from gateway.bridge import GatewayError
    with pytest.raises(GatewayError):
        GatewayService(wm, {}, sessions[0])
    prefix = f"bsc-close-{uuid.uuid4().hex}"
    buses = {n: can.Bus(interface="virtual", channel=wire.channel_name(prefix, n), ignore_config=True)
             for n in wm.buses}
    try:
        gw = GatewayService(wm, buses, sessions[0]).start()
        gw.close()
        gw.close()
    finally:
        for b in buses.values():
            b.shutdown()


def test_gateway_command_publishes_health_over_loopback():
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "gateway.cli", "gateway", "--interface", "virtual", "--channel", "bsc-cli",
         "--robot", "paper_robot", "--listen", ep, "--health-period", "0.1", "--duration", "20"],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        col = Collector(lambda got: any(isinstance(o, BusHealth) for _, o in got))
        with zenoh.open(make_config(connect=[ep])) as s:
            sub = s.declare_subscriber(keys.health("paper_robot"), col)
            ok = col.done.wait(30.0)
            sub.undeclare()
        assert ok, proc.stderr.read() if proc.poll() is not None else "no health received"
    finally:
        proc.terminate()
        out, err = proc.communicate(timeout=30)
    assert "bsc gateway: robot paper_robot" in out, err


def arm0_ft_then_close(sessions, keyexpr: str, want, *, before_close=None, **service_kw) -> list:
    """A gateway of the paper robot receives three F/T samples of arm0 only (their epoch never
    completes), drains, ``before_close(collected)``, closes; what a subscriber to ``keyexpr``
    got once ``want(collected)`` holds."""
    pub_s, sub_s = sessions
    robot = robot_description.load("paper_robot")
    wm = wire.WireMap.from_robot(robot)
    prefix = f"bsc-close-{uuid.uuid4().hex}"
    col = Collector(want)
    sub = sub_s.declare_subscriber(keyexpr, col)
    buses = {n: can.Bus(interface="virtual", channel=wire.channel_name(prefix, n), receive_own_messages=False,
                        ignore_config=True) for n in wm.buses}
    tx = can.Bus(interface="virtual", channel=wire.channel_name(prefix, "arm0"), receive_own_messages=False,
                 ignore_config=True)
    try:
        subscribed(pub_s, keyexpr)
        gw = GatewayService(robot, buses, pub_s, GatewayConfig().updated(service=service_kw)).start()
        sent = 0
        for c in range(3):
            for m in frames.encode_wrench(WrenchSample("arm0", 0, c, (1.0, 2.0, 3.0), (0.1, 0.2, 0.3))):
                tx.send(m)
                sent += 1
        end = time.monotonic() + 10.0         # drain() covers what the notifiers have received so far
        while gw.stats["received"] < sent and time.monotonic() < end:
            time.sleep(0.002)
        assert gw.drain(10.0) and gw.stats["processed"] == sent
        if before_close is not None:
            before_close(col.got)
        gw.close()
        assert col.done.wait(10.0), col.got
    finally:
        tx.shutdown()
        for b in buses.values():
            b.shutdown()
        sub.undeclare()
    return col.got


def _nothing_yet(got) -> None:
    assert not got                        # nothing computed yet: the epoch waits for its inputs


def test_epochs_flushed_at_close_are_still_published(sessions):
    """Epochs still waiting for inputs when the service closes are computed by the final flush
    (flagged, never good) and must reach subscribers, not vanish."""
    n_arms = len(robot_description.load("paper_robot").arms)
    got = arm0_ft_then_close(sessions, keys.efforts("paper_robot"),
                             lambda got: sum(isinstance(o, JointEfforts) for _, o in got) >= n_arms,
                             before_close=_nothing_yet)
    efforts = [o for _, o in got if isinstance(o, JointEfforts)]
    assert all(not e.good and any(f.startswith("missing:") for f in e.flags) for e in efforts)


def test_no_samples_publishes_efforts_but_no_sensor_samples(sessions):
    """``bsc gateway --no-samples``: decoded samples stay inside the gateway, efforts go out."""
    got = arm0_ft_then_close(sessions, keys.everything("paper_robot"),
                             lambda got: any(isinstance(o, JointEfforts) for _, o in got), publish_samples=False)
    assert not [k for k, _ in got if "/sensors/" in k]


def test_open_can_gives_each_bus_its_udp_port_by_robot_order(monkeypatch):
    """bsc gateway, record and replay open buses the same way: on udp_multicast a bus's port is
    that of its place in the robot's bus list (as the firmware sends), even when only some are
    opened (a replay of one bus)."""
    import contextlib

    from gateway.commands.gateway import channels, open_can

    opened = {}

    class FakeBus:
        def __init__(self, **kw):
            opened[kw["channel"]] = kw

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

    monkeypatch.setattr(can, "Bus", FakeBus)
    buses = ["arm0", "arm1", "spacecraft"]
    chans = channels(["spacecraft=239.74.163.3"], buses, every=False)
    with contextlib.ExitStack() as stack:
        open_can(stack, "udp_multicast", chans, buses, fd=True)
    assert opened == {"239.74.163.3": {"interface": "udp_multicast", "channel": "239.74.163.3",
                                       "ignore_config": True, "fd": True, "port": wire.udp_port(2),
                                       "bitrate": wire.BITRATE, "data_bitrate": wire.FD_DATA_BITRATE}}
    from gateway.cli import UserError
    with pytest.raises(UserError, match="missing arm1, spacecraft"):
        channels(["arm0=can0"], buses)
