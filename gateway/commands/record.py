"""``bsc record``: one MCAP file per session, raw CAN frames per bus and every zenoh sample.

CAN (``--interface``/``--channel`` as ``bsc gateway`` takes them): every frame of every bus on
``/can/<bus>``, as python-can received it. zenoh (``--zenoh KEYEXPR``, default
``bsc/<robot>/**``): every sample on its key as the topic, decoded by :mod:`gateway.codec` so
each channel has the dataclass's JSON schema; a payload that does not decode (or whose type
clashes with the key's earlier type) is counted by reason and kept raw on
``/zenoh/rejected``. The session context (URDF, DBCs, key scheme, version, robot name) goes
into every file. Ctrl-C or SIGTERM finish the file cleanly; the counts are printed at the end.
"""
from __future__ import annotations

import argparse
import base64
import threading
import time
from collections import Counter
from typing import Any, Mapping

REJECTED_TOPIC = "/zenoh/rejected"
REJECTED_SCHEMA = {
    "title": "bsc.ZenohRejected",
    "description": "A zenoh sample bsc record could not record as a typed sample.",
    "type": "object",
    "properties": {
        "key": {"type": "string", "description": "key expression of the sample"},
        "reason": {"type": "string"},
        "error": {"type": "string"},
        "payload": {"type": "string", "contentEncoding": "base64"},
    },
    "required": ["key", "reason", "error", "payload"],
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--robot", default=None, metavar="NAME|FILE",
                        help="robot description (default paper_robot)")
    parser.add_argument("--out", "-o", required=True, metavar="FILE.mcap", help="output file")
    parser.add_argument("--force", action="store_true", help="replace existing output files")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="stop after S seconds (default: until Ctrl-C / SIGTERM)")
    parser.add_argument("--split-size", type=float, default=None, metavar="MB",
                        help="start a new file every MB MiB (files <stem>_0000.mcap, ...)")
    parser.add_argument("--split-duration", type=float, default=None, metavar="S",
                        help="start a new file every S seconds")
    parser.add_argument("--scenario", default=None, metavar="FILE.toml",
                        help="attach the scenario file the session runs")
    from drivers.canbus import add_can_arguments

    add_can_arguments(parser.add_argument_group("CAN"),
                      interface_help="python-can interface (socketcan, virtual, ...); no CAN without it")
    parser.add_argument("--zenoh", dest="keyexpr", default=None, metavar="KEYEXPR",
                        help="zenoh key expression to record (default bsc/<robot>/**)")
    parser.add_argument("--no-zenoh", action="store_true", help="record CAN only")
    from gateway.zenoh_config import add_zenoh_arguments

    add_zenoh_arguments(parser)


class Recording:
    """Feeds a :class:`gateway.log.recorder.Recorder` from CAN buses and a zenoh subscription.

    Given open buses (logical name -> ``can.BusABC``) and/or an open zenoh session; owns only
    the notifiers and the subscriber it creates. A context manager; ``close()`` twice is fine.
    Nothing is lost silently: frames and samples the recorder refuses are counted in
    ``refused``, samples it cannot type in ``rejected`` (by reason). With ``robot`` (a
    :class:`robot_description.Robot`), its IMU and joint samples also make the frame tree on
    ``/tf`` and the URDF on ``/robot_description`` for Foxglove's 3D panel
    (:class:`gateway.log.foxglove.TransformWriter`).
    """

    def __init__(self, recorder, buses: Mapping[str, Any] | None = None, session=None,
                 keyexpr: str | None = None, robot=None):
        if session is not None and not keyexpr:
            raise ValueError("a zenoh session needs a key expression")
        self.recorder = recorder
        self.buses = dict(buses or {})
        self.session = session
        self.keyexpr = keyexpr
        self.frames: Counter[str] = Counter()
        self.samples: Counter[str] = Counter()       # by type name
        self.rejected: Counter[str] = Counter()      # by reason
        self.refused = 0
        self._lock = threading.Lock()
        self._notifiers: list = []
        self._subscriber = None
        self._closed = False
        self._declared = False
        self._log_declared = False          # the foxglove.Log topic of alerts
        self._tf = None                     # robot given: /tf and /robot_description from its samples
        if robot is not None:
            from gateway.log.foxglove import TransformWriter

            self._tf = TransformWriter(recorder, robot)

    def start(self) -> "Recording":
        import can

        if self._closed:
            raise RuntimeError("recording is closed")
        if self.session is not None and self._subscriber is None:
            if not self._declared:
                self.recorder.add_channel(REJECTED_TOPIC, REJECTED_SCHEMA)
                self._declared = True
            self._subscriber = self.session.declare_subscriber(self.keyexpr, self._on_sample)
        if not self._notifiers:
            for name, bus in self.buses.items():
                self._notifiers.append(can.Notifier(bus, [self._listener(name)], timeout=0.1))
        return self

    def _listener(self, bus: str):
        import can

        owner = self
        record_can = self.recorder.record_can

        class _Frames(can.Listener):
            def on_message_received(self, msg) -> None:
                if record_can(bus, msg):
                    owner.frames[bus] += 1       # one notifier thread per bus: no race
                else:
                    with owner._lock:
                        owner.refused += 1

            def stop(self) -> None:
                """Nothing to release."""

        return _Frames()

    def _on_sample(self, sample) -> None:
        # zenoh's callback thread: never raise out of here.
        key = "?"
        try:
            key = str(sample.key_expr)
            payload = sample.payload.to_bytes()
            self.on_payload(key, payload)
        except Exception as exc:  # noqa: BLE001 - counted, a callback must survive anything
            with self._lock:
                self.rejected[f"error:{type(exc).__name__}"] += 1

    def on_payload(self, key: str, payload: bytes) -> None:
        """Record one zenoh payload published on ``key``."""
        from drivers.samples import ImuSample, JointSample
        from gateway import codec
        from gateway.efforts import Alert

        try:
            obj = codec.decode(payload)
        except codec.CodecError as exc:
            self._reject(key, payload, "undecodable", exc)
            return
        try:
            ok = self.recorder.record(key, obj)
        except (TypeError, ValueError) as exc:     # another type already on this key, bad time
            self._reject(key, payload, "type_conflict", exc)
            return
        if ok and isinstance(obj, Alert):          # also as a foxglove.Log line (Foxglove's Log panel)
            ok = self._log_alert(obj)
        elif ok and self._tf is not None and isinstance(obj, (ImuSample, JointSample)):
            with self._lock:                       # the robot's frame tree for Foxglove's 3D panel
                ok = self._tf.sample(obj)
        with self._lock:
            if ok:
                self.samples[type(obj).__name__] += 1
            else:
                self.refused += 1

    def _log_alert(self, alert) -> bool:
        from gateway.log.foxglove import ALERT_LOG_TOPIC, LOG_SCHEMA, alert_log

        with self._lock:
            if not self._log_declared:
                self.recorder.add_channel(ALERT_LOG_TOPIC, LOG_SCHEMA)
                self._log_declared = True
        return self.recorder.record(ALERT_LOG_TOPIC, alert_log(alert), log_time_ns=alert.t_ns)

    def _reject(self, key: str, payload: bytes, reason: str, exc: Exception) -> None:
        ok = self.recorder.record(REJECTED_TOPIC, {
            "key": key, "reason": reason, "error": str(exc)[:500],
            "payload": base64.b64encode(payload).decode("ascii")}, log_time_ns=time.time_ns())
        with self._lock:
            self.rejected[reason] += 1
            if not ok:
                self.refused += 1

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for n in self._notifiers:
            n.stop()
        self._notifiers.clear()
        if self._subscriber is not None:
            try:
                self._subscriber.undeclare()
            except Exception:  # noqa: BLE001 - a session closed first must not mask close()
                pass
            self._subscriber = None

    def __enter__(self) -> "Recording":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def summary(self) -> list[str]:
        """The end-of-session lines: what was recorded, what was not."""
        st = self.recorder.stats
        lines = []
        if self.buses:
            lines.append(f"CAN frames: {sum(self.frames.values())}"
                         + (" (" + ", ".join(f"{b} {self.frames[b]}" for b in self.buses) + ")"))
        if self.session is not None:
            lines.append(f"zenoh samples: {sum(self.samples.values())}"
                         + (" (" + ", ".join(f"{k} {v}" for k, v in sorted(self.samples.items()))
                            + ")" if self.samples else ""))
            lines.append("zenoh rejected: " + (", ".join(
                f"{k} {v}" for k, v in sorted(self.rejected.items())) or "0")
                + (f" (kept raw on {REJECTED_TOPIC})" if self.rejected else ""))
        lines.append(f"recorder: {st.flushed} messages in the file(s), {st.dropped} dropped (queue full "
                     f"{st.dropped_queue_full}, write error {st.dropped_write_error}, after close "
                     f"{st.dropped_closed}), {st.files} file(s), {st.bytes_written} bytes"
                     + (f"; stopped: {st.error}" if st.error else ""))
        return lines


def _positive(name: str, value: float | None) -> None:
    from gateway.cli import UserError

    if value is not None and not value > 0:
        raise UserError(f"{name} {value}: must be positive")


def bus_rates(args: argparse.Namespace, chans: dict) -> str:
    """The bit rates the buses open with (``bsc.session`` ``bus_rates``), "" without CAN."""
    if not chans:
        return ""
    from drivers.canbus import BusOptions, describe

    return describe(BusOptions.from_args(args), args.interface, chans.values(), fd=args.fd)


def run(args: argparse.Namespace) -> int:
    import contextlib
    from pathlib import Path

    import robot_description
    from drivers.wire import WireMap
    from gateway import keys
    from gateway.cli import UserError
    from gateway.log.recorder import Recorder
    from gateway.log.context import session_context

    _positive("--duration", args.duration)
    _positive("--split-size", args.split_size)
    _positive("--split-duration", args.split_duration)
    if args.channel and not args.interface:
        raise UserError("--channel needs --interface")
    from gateway.commands import check_interface

    check_interface(args)
    if args.interface and not args.channel:
        raise UserError("--interface needs --channel PREFIX or BUS=CHANNEL")
    if args.no_zenoh and not args.interface:
        raise UserError("nothing to record: --no-zenoh without --interface")
    robot = robot_description.load(args.robot)
    wm = WireMap.from_robot(robot)
    chans: dict[str, str] = {}
    if args.interface:
        from gateway.commands.gateway import channels

        chans = channels(args.channel, list(wm.buses))
    keyexpr = None if args.no_zenoh else (args.keyexpr or keys.everything(robot.name))
    scenario = None
    if args.scenario is not None:
        scenario = Path(args.scenario).read_text()
    rotate_bytes = None if args.split_size is None else max(int(args.split_size * (1 << 20)),
                                                            4 * 128 * 1024)
    out = Path(args.out)
    try:
        rec = Recorder(out, rotate_bytes=rotate_bytes, rotate_s=args.split_duration,
                       overwrite=args.force)
    except FileExistsError:
        raise UserError(f"{out} exists (use --force to replace it)") from None

    from gateway.commands import stop_on_sigterm

    stop, restore = stop_on_sigterm()
    recording = None
    try:
        with contextlib.ExitStack() as stack:
            stack.callback(rec.close)
            rec.add_session_context(**session_context(
                robot, fd=args.fd, scenario_text=scenario,
                extra={"command": "bsc record", "interface": args.interface or "",
                       "channels": ",".join(f"{b}={c}" for b, c in chans.items()),
                       "zenoh_keyexpr": keyexpr or "",
                       "bus_rates": bus_rates(args, chans)}))
            buses = {}
            if chans:
                from gateway.commands.gateway import open_can

                from drivers.canbus import BusOptions

                buses = open_can(stack, args.interface, chans, list(wm.buses), fd=args.fd,
                                 options=BusOptions.from_args(args))
            session = None
            if keyexpr is not None:
                import zenoh

                from gateway.zenoh_config import config_from_args

                session = stack.enter_context(zenoh.open(config_from_args(args)))
            recording = stack.enter_context(Recording(rec, buses, session, keyexpr, robot=robot))
            what = ", ".join([f"CAN {b}={c}" for b, c in chans.items()]
                             + ([f"zenoh {keyexpr}"] if keyexpr else []))
            print(f"bsc record: robot {robot.name} -> {out}: {what}", flush=True)
            end = None if args.duration is None else time.monotonic() + args.duration
            try:
                # a write failure (a full disk) stops the recording at once: closing raises it
                while not stop.is_set() and rec.error is None:
                    wait = 0.1 if end is None else min(0.1, end - time.monotonic())
                    if wait <= 0:
                        break
                    stop.wait(wait)
            except KeyboardInterrupt:
                pass
            recording.close()
    finally:
        restore()
        if recording is not None:
            for line in recording.summary():
                print(f"bsc record: {line}", flush=True)
            print("bsc record: wrote " + ", ".join(str(p) for p in rec.paths), flush=True)
    return 0
