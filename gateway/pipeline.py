"""Drivers and estimator in one single-threaded core: raw CAN frames in, everything out.

:class:`Pipeline` is what ``bsc gateway`` runs behind its buses, what ``bsc replay`` runs over a
recorded log and what ``bsc demo`` and the simulated series run in lockstep. Both halves are
compiled kernels that keep all their state in arrays (:class:`drivers.kernel.DriverCore`,
:class:`gateway.estimator.core.EstimatorCore`), so frames may be fed one at a time
(:meth:`Pipeline.feed`, the live gateway) or as arrays of any length
(:meth:`Pipeline.feed_frames`, a replay): the same frames in the same order give the same samples
and the same efforts, bit for bit, whatever the split (the estimator's sync policy also makes
the result independent of how buses interleave: see :mod:`gateway.estimator.core`).

Every decoded sample, every computed effort and (on request) every health report goes to
``emit(key, obj)`` synchronously, with the zenoh key of :mod:`gateway.keys`; within one call the
samples come first, then the efforts they completed (one frame per call: exactly the order of
the first wave). While ``emit`` runs, :attr:`Pipeline.log_ns` is the timestamp of the frame
that produced the object (its log time in a recording). Nothing here does I/O or owns a thread.

The thruster filter's learned per-valve wrenches (:class:`gateway.efforts.ValveWrenches`, what
``bsc control``'s thruster loop allocates with) are emitted at most once per
:data:`VALVE_WRENCH_PERIOD_NS` of sensor time: right after the first valve command sample of each
such window has been fed, the filter as of the latest epoch computed, with that epoch's time and
thruster quality (none again before a newer epoch). The estimator is fed up to that sample, then
on: where the record is taken depends only on the samples, never on how the frames were split
into calls, so a replay reproduces it byte for byte. Within one call the records come before the
efforts the call computed (as the samples do): their place among the efforts depends on the split,
their bytes and their order on their key do not.
"""
from __future__ import annotations

from typing import Callable

import can
import numpy as np

from gateway.errors import GatewayError
from drivers import wire
from drivers.health import DEFAULT_TIMING, SourceTiming
from drivers.kernel import DriverCore, columns_from_messages
from drivers.samples import ImuSample, JointSample, ThrusterCommand, TorqueCommand, ValveCommand, WrenchSample
from gateway import keys
from gateway.efforts import JointEfforts, ThrusterEffort, ValveWrenches
from gateway.estimator.core import VALVES, CoreSettings, EstimatorCore
from robot_description import Robot
from robot_description.thrusters import ThrusterLayout

Emit = Callable[[str, object], None]
RowsOut = Callable[[np.ndarray, np.ndarray], None]      # (rows, log time of each row)
# the attribute that picks the key of a sample type (None: one key for the type)
_KEY_ATTR = {WrenchSample: "device", JointSample: "device", TorqueCommand: "device", JointEfforts: "arm",
             ImuSample: None, ThrusterCommand: None, ValveCommand: None, ThrusterEffort: None,
             ValveWrenches: None}
VALVE_WRENCH_PERIOD_NS = 5_000_000      # the learned per-valve wrenches: at most one record per 5 ms (200 Hz)


class PipelineError(GatewayError, ValueError):
    """The pipeline cannot be built as asked (a model that is not the robot's, ...)."""


class Pipeline:
    """``Pipeline(robot, emit=...)``; ``model_robot`` is the gateway's belief of the robot (default
    ``robot``: e.g. :func:`robot_description.perturbed` for a deliberately wrong model), with the
    robot's arms and joints; ``layout`` the nominal thruster layout (the filter's prior);
    ``timing``: how frame timestamps relate to the devices' clocks
    (:class:`drivers.health.SourceTiming`); ``samples=False`` leaves decoded samples out of the
    emits (they are still decoded, counted and estimated from). ``on_samples`` / ``on_efforts``
    take the rows themselves (the drivers' event rows, the estimator's effort rows) with each
    row's log time, instead of objects to ``emit``: for outputs that encode rows directly."""

    def __init__(self, robot: Robot, *, emit: Emit, model_robot: Robot | None = None,
                 layout: ThrusterLayout | None = None, fd: bool = False, estimate: bool = True,
                 settings: CoreSettings | None = None, timing: SourceTiming = DEFAULT_TIMING,
                 samples: bool = True, on_samples: RowsOut | None = None, on_efforts: RowsOut | None = None,
                 on_valves: RowsOut | None = None):
        self.robot = robot
        self.wire = wire.WireMap.from_robot(robot)
        self.name = self.wire.robot
        self.buses = list(self.wire.buses)
        self._bus_index = {b: i for i, b in enumerate(self.buses)}
        self.emit = emit
        self.emit_samples = samples
        self.on_samples, self.on_efforts, self.on_valves = on_samples, on_efforts, on_valves
        self.drivers = DriverCore(self.wire, fd=fd, timing=timing)
        model = model_robot or robot
        if [(a.name, tuple(a.joint_names)) for a in model.arms] != [(a.name, tuple(a.joint_names)) for a in robot.arms]:
            raise PipelineError(f"the model {model.name!r} must have the arms and joints of the robot {robot.name!r}")
        self.estimator = EstimatorCore(model, layout=layout, settings=settings) if estimate else None
        self._one_log = np.zeros(1, dtype=np.int64)
        self._valve_window = np.iinfo(np.int64).min     # the latest valve-wrench window opened
        self._last_epoch: tuple[int, np.ndarray] | None = None     # (t_ns, thruster flags) of the latest effort row
        self._valves_t: int | None = None               # the epoch of the latest valve wrenches emitted
        # the valve wrenches taken in the current call (rows, each one's log time), out before its efforts
        self._valves = np.zeros(4, dtype=self.estimator.valve_dtype) if self.estimator is not None else None
        self._valves_log: list[int] = []
        self._keys: dict = {}                    # (type, device or arm) -> zenoh key
        self.log_ns = 0
        self._unknown = 0
        self.frames = 0
        self.samples = 0
        self.efforts = 0

    @property
    def unknown_bus(self) -> int:
        """Frames fed for a bus this robot does not have (counted, never decoded)."""
        return self._unknown + self.drivers.unknown_bus

    # -- input ---------------------------------------------------------------------------------
    def feed(self, bus: str, msg: can.Message, log_ns: int | None = None) -> None:
        """One raw frame from ``bus``. Never raises on bad frames (they are counted by reason).
        ``log_ns``: the log time of what it produces (default: its timestamp)."""
        i = self._bus_index.get(bus)
        if i is None:
            self._unknown += 1
            return
        one = columns_from_messages([(i, msg)])
        if log_ns is None:
            self.feed_frames(one)
        else:
            self._one_log[0] = log_ns
            self.feed_frames(one, self._one_log)

    def rows_of(self, pairs) -> tuple[np.ndarray, list[int]]:
        """``(bus, can.Message)`` pairs -> (:data:`drivers.kernel.FRAME_DTYPE` rows, the index of
        each row's pair); pairs of a bus the robot does not have are counted and left out."""
        index = self._bus_index
        kept = [k for k, (bus, _) in enumerate(pairs) if bus in index]
        self._unknown += len(pairs) - len(kept)
        return columns_from_messages([(index[pairs[k][0]], pairs[k][1]) for k in kept]), kept

    def feed_frames(self, frames: np.ndarray, log_ns: np.ndarray | None = None) -> None:
        """Frames as :data:`drivers.kernel.FRAME_DTYPE` rows (``bus`` = index into
        :attr:`buses`), in arrival order; ``log_ns`` (one per frame) the log times of what they
        produce (default: their timestamps)."""
        self.frames += len(frames)
        events = self.drivers.feed(frames)
        if not len(events):
            return
        t_frame = frames["t_ns"] if log_ns is None else log_ns
        self.samples += len(events)
        if self.emit_samples:
            if self.on_samples is not None:
                self.on_samples(events, t_frame[events["frame"]])
            else:
                emit = self.emit
                frame_of = events["frame"].tolist()
                for k, obj in enumerate(self.drivers.to_samples(events)):
                    self.log_ns = int(t_frame[frame_of[k]])
                    emit(self.key(obj), obj)
        est = self.estimator
        if est is not None:
            cuts = self._valve_cuts(events)
            if not cuts:                                   # no valve wrenches to take here
                rows = est.feed(events)
            else:
                # the valve wrenches taken at each cut (after a valve command that opens a
                # window) in the same compiled pass; they go out before the call's efforts (one
                # encoding of the batch)
                rows, n_at, snap_w, snap_s = est.feed_cuts(events, cuts)
                frame_of = events["frame"]
                for c, (hi, n) in enumerate(zip(cuts, n_at.tolist())):
                    last = self._last_epoch if n == 0 else (int(rows["t_ns"][n - 1]), rows["flags"][n - 1])
                    self._valve_wrenches(int(t_frame[frame_of[hi - 1]]), last, snap_w[c], snap_s[c])
                if self._valves_log:
                    self._emit_valves()
            if len(rows):
                self._efforts(rows, t_frame[events["frame"][rows["cause"]]])
            alarms = est.thruster_alarms()
            if alarms:
                # each at the log time of its own epoch (frame clock + this batch's offset to log
                # time), not the batch's last frame: the same whatever the batch
                offset = int(t_frame[-1]) - int(frames["t_ns"][-1])
                self._thruster_alarms(alarms, offset)

    def flush(self) -> None:
        """End of input: compute the epochs still waiting for members (log time: the last frame's)."""
        if self.estimator is not None:
            rows = self.estimator.flush()
            if len(rows):
                self._efforts(rows, np.full(len(rows), self.log_ns, dtype=np.int64))
            alarms = self.estimator.thruster_alarms()
            if alarms:
                self._thruster_alarms(alarms)

    def _valve_cuts(self, events: np.ndarray) -> list[int]:
        """Where to take the valve wrenches in ``events``: the index after each valve command
        sample that opens a new window of :data:`VALVE_WRENCH_PERIOD_NS`."""
        v = np.flatnonzero(events["kind"] == VALVES)
        if not len(v):
            return []
        seen = self._valve_window                # the latest window opened, so far
        cuts = []
        for i, w in zip(v.tolist(), (events["t_ns"][v] // VALVE_WRENCH_PERIOD_NS).tolist()):
            if w > seen:                         # a few per call: a loop costs less than numpy's calls
                cuts.append(i + 1)
                seen = w
        self._valve_window = seen
        return cuts

    def _valve_wrenches(self, log_ns: int, last: tuple[int, np.ndarray] | None, wrench: np.ndarray,
                        sigma: np.ndarray) -> None:
        """Keep the thruster filter's learned per-valve wrenches ``wrench``, ``sigma`` (as
        :meth:`EstimatorCore.valve_row` gives them) as of the latest epoch computed (once per
        epoch; ``last``: its time and effort flags), for ``bsc/<robot>/efforts/valves`` at log time
        ``log_ns``: out with the others of the call (:meth:`_emit_valves`)."""
        if last is None or last[0] == self._valves_t:
            return
        self._valves_t = last[0]
        k = len(self._valves_log)
        if k == len(self._valves):
            self._valves = np.concatenate([self._valves, np.zeros_like(self._valves)])
        self._valves["wrench"][k] = wrench
        self._valves["force_sigma_n"][k] = sigma
        self._valves["t_ns"][k] = last[0]
        self._valves["flags"][k] = last[1]
        self._valves_log.append(log_ns)

    def _emit_valves(self) -> None:
        """The valve wrenches taken in this call: as rows to :attr:`on_valves` (valid until the
        next call) or as :class:`ValveWrenches` objects to ``emit``."""
        rows, logs = self._valves[:len(self._valves_log)], self._valves_log
        self._valves_log = []
        if self.on_valves is not None:
            self.on_valves(rows, np.array(logs, dtype=np.int64))
        else:
            self.emit_valves(rows, logs, self.emit)

    def emit_valves(self, rows: np.ndarray, log_ns: list[int], emit: Emit) -> None:
        """Valve rows as objects to ``emit``, :attr:`log_ns` set for each."""
        key = keys.valve_wrenches(self.name)
        for obj, t in zip(self.estimator.valve_objects(rows), log_ns):
            self.log_ns = t
            emit(key, obj)

    def _thruster_alarms(self, alarms: list[dict], offset: int | None = None) -> None:
        """The estimator's thruster faults (gateway/estimator/fdi.py) as alerts on
        ``bsc/<robot>/alerts``: critical for a stuck valve, a warning for a partial loss, a
        leak or a misalignment; evidence: the thruster, the fault's size (fraction of nominal
        thrust; a misalignment's tilt, degrees), the GLR or CUSUM statistic and the type's code
        (0 stuck open, 1 leak, 2 stuck closed, 3 partial loss, 5 misalignment). ``offset``: frame
        clock to log time (each alert then at its epoch's log time); None: at :attr:`log_ns`."""
        from gateway.efforts import Alert
        from gateway.estimator import fdi

        for a in alarms:
            if offset is not None:
                self.log_ns = a["t_ns"] + offset
            j, fault = a["thruster"], a["fault"]
            stuck = fault in ("stuck open", "stuck closed")
            alert = Alert(self.name, "thruster", f"thruster{j}", fdi.RULE, "critical" if stuck else "warning",
                          "raised", a["detected_t_ns"], a["t_ns"],
                          f"thruster {j}: {fault} ({fdi.size_text(fault, a['theta'])})",
                          (("thruster", float(j)), ("theta", a["theta"]), ("stat", a["stat"]),
                           ("type", float(fdi.TYPES.index(fault)))))
            self.emit(keys.alerts(self.name), alert)

    def _efforts(self, rows: np.ndarray, log_ns: np.ndarray) -> None:
        self.efforts += len(rows) * (self.estimator.n_arms + 1)
        self._last_epoch = (int(rows["t_ns"][-1]), rows["flags"][-1].copy())
        if self.on_efforts is not None:
            self.on_efforts(rows, log_ns)
        else:
            self.emit_efforts(rows, log_ns.tolist(), self.emit)

    def emit_efforts(self, rows: np.ndarray, log_ns: list[int], emit: Emit) -> None:
        """Effort rows as objects to ``emit``, :attr:`log_ns` set for each (one log time per row)."""
        n_per_row = self.estimator.n_arms + 1
        for k, obj in enumerate(self.estimator.efforts(rows)):
            self.log_ns = log_ns[k // n_per_row]
            emit(self.key(obj), obj)

    def key(self, obj) -> str:
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

    # -- health --------------------------------------------------------------------------------
    def health(self, now_ns: int) -> list:
        """Snapshots of every bus and device (resets the measured-load window)."""
        return self.drivers.health_list(now_ns)

    def emit_health(self, now_ns: int) -> None:
        for h in self.health(now_ns):
            self.emit(keys.for_sample(self.name, h), h)

    @property
    def stats(self) -> dict[str, int]:
        est = self.estimator
        return {"frames": self.frames, "samples": self.samples, "efforts": self.efforts,
                "epochs": est.epochs if est else 0, "good_epochs": est.good if est else 0,
                "late_samples": est.late if est else 0, "unknown_bus": self.unknown_bus}

