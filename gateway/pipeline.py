"""Drivers and estimator in one single-threaded core: raw CAN frames in, everything out.

:class:`Pipeline` is what ``bsc gateway`` runs behind its buses, what ``bsc replay`` runs over a
recorded log and what ``bsc demo`` and the simulated series run in lockstep. Frames are fed one
at a time, in arrival order, with the bus they came from; every decoded sample, every computed
effort and (on request) every health report goes to ``emit(key, obj)`` synchronously, with the
zenoh key of :mod:`gateway.keys`. Nothing here does I/O or owns a thread, so the same frames in
the same order always give the same emits (the estimator's sync policy also makes the result
independent of how buses interleave: see :mod:`gateway.estimator.live`).
"""
from __future__ import annotations

from typing import Callable

import can

from drivers import wire
from drivers.devices import BusDispatcher, listeners_for
from drivers.health import DEFAULT_TIMING, SourceTiming
from drivers.samples import ImuSample, JointSample, ThrusterCommand, TorqueCommand, ValveCommand, WrenchSample
from gateway import keys
from gateway.efforts import JointEfforts, ThrusterEffort
from gateway.estimator.live import LiveEstimator, LiveSettings
from robot_description import Robot
from robot_description.thrusters import ThrusterLayout

Emit = Callable[[str, object], None]
# the attribute that picks the key of a sample type (None: one key for the type)
_KEY_ATTR = {WrenchSample: "device", JointSample: "device", TorqueCommand: "device", JointEfforts: "arm",
             ImuSample: None, ThrusterCommand: None, ValveCommand: None, ThrusterEffort: None}


class Pipeline:
    """``Pipeline(robot, emit=...)``; ``model_robot`` is the gateway's belief of the robot (default
    ``robot``: e.g. :func:`robot_description.perturbed` for a deliberately wrong model);
    ``timing``: how frame timestamps relate to the devices' clocks (:class:`drivers.health.SourceTiming`)."""

    def __init__(self, robot: Robot, *, emit: Emit, model_robot: Robot | None = None,
                 layout: ThrusterLayout | None = None, fd: bool = False, estimate: bool = True,
                 settings: LiveSettings | None = None, timing: SourceTiming = DEFAULT_TIMING):
        self.robot = robot
        self.wire = wire.WireMap.from_robot(robot)
        self.name = self.wire.robot
        self.buses = list(self.wire.buses)
        self.emit = emit
        self._listeners = {}
        for name, spec in self.wire.buses.items():
            monitor, drivers = listeners_for(spec, self._on_sample, fd, timing)
            self._listeners[name] = [monitor, *drivers]
        self.monitors = {b: ls[0] for b, ls in self._listeners.items()}
        self._feeders = {b: BusDispatcher(ls[0], ls[1:]).feed for b, ls in self._listeners.items()}
        self.estimator = (LiveEstimator(model_robot or robot, self._on_effort, layout=layout, settings=settings)
                          if estimate else None)
        self._add = self.estimator.add if self.estimator is not None else None
        self._keys: dict = {}                    # (type, device or arm) -> zenoh key
        self.frames = 0
        self.unknown_bus = 0
        self.samples = 0
        self.efforts = 0

    def feed(self, bus: str, msg: can.Message) -> None:
        """One raw frame from ``bus``. Never raises on bad frames (they are counted by reason)."""
        feeder = self._feeders.get(bus)
        if feeder is None:
            self.unknown_bus += 1
            return
        self.frames += 1
        feeder(msg)

    def flush(self) -> None:
        """End of input: compute the epochs still waiting for members."""
        if self.estimator is not None:
            self.estimator.flush()

    def _key(self, obj) -> str:
        """``keys.for_sample`` (each key expression is built and checked once, then cached)."""
        cls = obj.__class__
        attr = _KEY_ATTR.get(cls, False)
        if attr is False:                        # another type: not cached
            return keys.for_sample(self.name, obj)
        k = cls if attr is None else (cls, getattr(obj, attr))
        key = self._keys.get(k)
        if key is None:
            key = self._keys[k] = keys.for_sample(self.name, obj)
        return key

    def _on_sample(self, sample) -> None:
        self.samples += 1
        self.emit(self._key(sample), sample)
        if self._add is not None:
            self._add(sample)

    def _on_effort(self, effort) -> None:
        self.efforts += 1
        self.emit(self._key(effort), effort)

    def health(self, now_ns: int) -> list:
        """Snapshots of every bus and device (resets the measured-load window)."""
        out = []
        for listeners in self._listeners.values():
            out.append(listeners[0].health(now_ns))
            for d in listeners[1:]:
                out.extend(d.health(now_ns))
        return out

    def emit_health(self, now_ns: int) -> None:
        for h in self.health(now_ns):
            self.emit(keys.for_sample(self.name, h), h)

    @property
    def stats(self) -> dict[str, int]:
        est = self.estimator
        return {"frames": self.frames, "samples": self.samples, "efforts": self.efforts,
                "epochs": est.epochs if est else 0, "good_epochs": est.good if est else 0,
                "late_samples": est.late if est else 0, "unknown_bus": self.unknown_bus}
