"""A zenoh router killed and restarted mid-run: publications resume with no manual step.

The router is a zenoh session in router mode in a subprocess (so it can be SIGKILLed), listening
on tcp/127.0.0.1:PORT. A publisher and a subscriber, client sessions of this process, connect to
it. After the kill, the SAME sessions (never reopened, the subscriber never redeclared) reconnect
to a new router on the same port, redeclare their interests, and samples flow again; once they
flow, nothing is lost.

Client mode reconnects with zenoh's defaults (first retry after ``connect/retry/period_init_ms``
= 1 s); the ``fast-retry`` case sets a shorter retry on top of ``make_config``. Waits are for
conditions; the bounds only turn a hang into a failure.
"""
from __future__ import annotations

import json
import selectors
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import zenoh

from gateway.zenoh_config import make_config
from support import free_port

ROOT = Path(__file__).resolve().parents[3]
KEY = "bsc/restart_test/alerts"
WAIT_S = 15.0
FAST_RETRY = {"period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 2}

ROUTER = r"""
import sys
import zenoh
from gateway.zenoh_config import make_config
with zenoh.open(make_config(listen=[sys.argv[1]], mode="router")) as s:
    print("ready", s.zid(), flush=True)
    sys.stdin.read()          # until the test closes stdin (or kills the process)
"""


class Router:
    def __init__(self, endpoint: str):
        self.proc = subprocess.Popen([sys.executable, "-c", ROUTER, endpoint], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, cwd=ROOT)
        with selectors.DefaultSelector() as sel:
            sel.register(self.proc.stdout, selectors.EVENT_READ)
            line = self.proc.stdout.readline().split() if sel.select(WAIT_S) else []
        if line[:1] != ["ready"]:
            self.stop()
            pytest.fail(f"the router did not start on {endpoint} (exit {self.proc.poll()})")
        self.zid = line[1]

    def kill(self) -> int:
        self.proc.send_signal(signal.SIGKILL)
        return self.proc.wait(WAIT_S)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.stdin.close()
            try:
                self.proc.wait(WAIT_S)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.proc.stdout.close()
        if not self.proc.stdin.closed:
            self.proc.stdin.close()


class Inbox:
    def __init__(self):
        self.seqs: list[int] = []
        self.cond = threading.Condition()

    def __call__(self, sample):
        with self.cond:
            self.seqs.append(int(sample.payload.to_bytes()))
            self.cond.notify_all()

    def wait(self, pred, timeout: float) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: pred(self.seqs), timeout)


class Pump:
    """Publishes 1, 2, 3, ... one sample per turn."""

    def __init__(self, session, inbox: Inbox):
        self.pub = session.declare_publisher(KEY, congestion_control=zenoh.CongestionControl.BLOCK)
        self.inbox, self.seq = inbox, 0

    def put(self) -> int:
        self.seq += 1
        self.pub.put(str(self.seq).encode())
        return self.seq

    def until(self, pred, what: str, turn_s: float = 0.05) -> None:
        """Keep publishing until ``pred(received)``: one put per turn, each turn ends as soon as
        the condition holds (or after ``turn_s``)."""
        for _ in range(int(WAIT_S / turn_s)):
            self.put()
            if self.inbox.wait(pred, turn_s):
                return
        pytest.fail(f"never: {what}")


@pytest.mark.parametrize("retry", [None, FAST_RETRY], ids=["default-retry", "fast-retry"])
def test_publications_resume_after_the_router_restarts(retry):
    endpoint = f"tcp/127.0.0.1:{free_port()}"

    def client():
        conf = make_config(connect=[endpoint], mode="client")
        if retry:
            conf.insert_json5("connect/retry", json.dumps(retry))
        return conf

    router = Router(endpoint)
    try:
        with zenoh.open(client()) as sub_s, zenoh.open(client()) as pub_s:
            inbox = Inbox()
            sub = sub_s.declare_subscriber(KEY, inbox)
            pump = Pump(pub_s, inbox)
            try:
                pump.until(lambda got: len(got) > 0, "a first sample through the router")
                assert [str(z) for z in pub_s.info.routers_zid()] == [router.zid]

                assert router.kill() == -signal.SIGKILL
                outage_first = pump.seq + 1
                for _ in range(10):                       # publishing into the void must not raise
                    pump.put()
                router = Router(endpoint)                 # same port, a new router (new zid)
                restart = pump.seq
                pump.until(lambda got: got[-1] > restart, "a sample published after the restart")
                assert [str(z) for z in pub_s.info.routers_zid()] == [router.zid]
                assert [str(z) for z in sub_s.info.routers_zid()] == [router.zid]

                # reconnected: from now on every sample arrives, in order
                first = pump.seq + 1
                last = first + 199
                while pump.seq < last:
                    pump.put()
                assert inbox.wait(lambda got: got[-1] == last, WAIT_S), "the last sample never came"
                with inbox.cond:
                    seqs = list(inbox.seqs)
                assert seqs[-200:] == list(range(first, last + 1))
                assert seqs == sorted(seqs)               # nothing duplicated or reordered
                assert not set(range(outage_first, outage_first + 10)) & set(seqs)   # no router, no delivery
            finally:
                pump.pub.undeclare()
                sub.undeclare()
    finally:
        router.stop()
