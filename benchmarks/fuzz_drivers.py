"""Fuzz the CAN drivers: ``python -m benchmarks.fuzz_drivers --frames 1000000`` (on demand).

Random and mutated frames go through every listener of every bus of a robot's wire map
(:func:`drivers.devices.listeners_for`: the BusMonitor and each device driver), exactly as a
``can.Notifier`` would call them. The contract under test (drivers/devices.py): a frame can never
raise out of a driver; whatever a bus delivers is either decoded into a valid sample or rejected
and counted by reason. Printed: frames/s, samples accepted, exceptions (must be 0, exit 1
otherwise) and the rejections by reason. A fixed seed makes a run reproducible.

Frame mix per bus (weights in ``MIX``):

- ``valid``: the next frame of a stream of correctly encoded samples (so assemblies complete
  and the decoders see real data, including clamped values);
- ``mutated``: the next valid frame of that stream with one to three of ``MUTATIONS`` applied: bit flips, truncated or
  extended data, a DLC that disagrees with the data, FD / remote / error / extended-id flags, a
  neighbouring or foreign id, a counter from another sample;
- ``random``: any id (11 or 29 bit), any length (classic or FD), any flags, random bytes.

tests/drivers/test_fuzz.py runs a short fixed-seed campaign in CI.
"""
from __future__ import annotations

import argparse
import math
import os
import random
import sys
import time
import typing
from collections import Counter
from dataclasses import dataclass, field, fields

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import can  # noqa: E402

from drivers import devices, frames, wire  # noqa: E402
from drivers.samples import (ImuSample, JointSample, Sample, ThrusterCommand, TorqueCommand,  # noqa: E402
                             WrenchSample)

SAMPLE_TYPES = typing.get_args(Sample)     # whatever the drivers may emit, current and future
FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
MIX = (("valid", 6), ("mutated", 3), ("random", 1))


@dataclass
class Report:
    frames: int = 0
    samples: int = 0
    seconds: float = 0.0
    kinds: Counter = field(default_factory=Counter)          # frames per mix kind
    mutations: Counter = field(default_factory=Counter)      # mutations applied, by name
    rejected: Counter = field(default_factory=Counter)       # bus + device rejections by reason
    lost: int = 0                                            # counter values skipped (not rejections)
    exceptions: Counter = field(default_factory=Counter)     # "<listener>: <exception type>"
    first_failure: str = ""                                  # the first frame that raised, for a repro
    bad_samples: int = 0                                     # decoded samples that broke an invariant

    @property
    def frames_per_s(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else float("nan")


# --- valid traffic ---------------------------------------------------------------------------

def _vec(r: random.Random, lim: float) -> tuple[float, float, float]:
    # mostly inside the range, sometimes past it (the encoder clamps: saturated samples)
    return tuple(r.uniform(-lim, lim) * (3.0 if r.random() < 0.05 else 1.0) for _ in range(3))


def valid_stream(spec: wire.BusSpec, r: random.Random, cycles: int = 256) -> list[can.Message]:
    """Correctly encoded frames of ``cycles`` device cycles on one bus, in sending order (256: the
    stream loops without a jump of the 8-bit sample counters)."""
    out: list[can.Message] = []
    hb_nodes = [i - wire.HEARTBEAT_BASE for i in sorted(spec.ids) if i >= wire.HEARTBEAT_BASE]
    for k in range(cycles):
        t = k * 1_000_000
        if spec.kind == "arm":
            out += frames.encode_wrench(WrenchSample(spec.arm, t, k, _vec(r, 1500.0), _vec(r, 1500.0),
                                                     status=r.choice((0, 0, 0, 2, 8))))
            for j, name in enumerate(spec.joints):
                out.append(frames.encode_joint(JointSample(f"{spec.arm}/{name}", t, k, r.uniform(-4e3, 4e3) / 1e3,
                                                           r.uniform(-9.0, 9.0), status=r.choice((0, 0, 1, 4))), j))
            out += frames.encode_torque_commands([TorqueCommand(f"{spec.arm}/{n}", t, k, r.uniform(-2e3, 2e3))
                                                  for n in spec.joints])
        else:
            q = [r.gauss(0, 1) for _ in range(4)]
            n = math.sqrt(sum(x * x for x in q)) or 1.0
            out += frames.encode_imu(ImuSample(t, k, tuple(x / n for x in q), _vec(r, 2.0), _vec(r, 4.0),
                                               status=r.choice((0, 0, 1, 0x100))))
            out += frames.encode_thruster(ThrusterCommand(t, k, _vec(r, 1600.0), _vec(r, 1600.0),
                                                          valves=r.getrandbits(32)))
        if hb_nodes and k % 10 == 0:
            out.append(frames.encode_heartbeat(r.choice(hb_nodes), k, r.choice((0x05, 0x05, 0x7F, 0x80))))
    return out


# --- mutations -------------------------------------------------------------------------------

def _copy(m: can.Message, **kw) -> can.Message:
    a = dict(arbitration_id=m.arbitration_id, data=bytes(m.data), is_extended_id=m.is_extended_id,
             is_remote_frame=m.is_remote_frame, is_error_frame=m.is_error_frame, is_fd=m.is_fd,
             bitrate_switch=m.bitrate_switch, dlc=m.dlc, timestamp=m.timestamp)
    a.update(kw)
    if "data" in kw and "dlc" not in kw:
        a["dlc"] = len(a["data"])
    return can.Message(check=False, **a)


def _flip_bits(m, r, ids):
    data = bytearray(m.data)
    if not data:
        return _copy(m, data=bytes([r.getrandbits(8)]))
    for _ in range(r.randint(1, 4)):
        i = r.randrange(len(data) * 8)
        data[i // 8] ^= 1 << (i % 8)
    return _copy(m, data=bytes(data))


def _truncate(m, r, ids):
    return _copy(m, data=bytes(m.data)[:r.randrange(max(len(m.data), 1))])


def _extend(m, r, ids):
    return _copy(m, data=bytes(m.data) + r.randbytes(r.randint(1, 8)))


def _dlc_mismatch(m, r, ids):
    return _copy(m, dlc=r.choice([d for d in range(16) if d != len(m.data)]))


def _fd(m, r, ids):
    data = bytes(m.data)[:64]
    n = r.choice([x for x in FD_LENGTHS if x >= len(data)])
    return _copy(m, data=data + bytes(n - len(data)), is_fd=True, bitrate_switch=r.random() < 0.5)


def _remote(m, r, ids):
    return _copy(m, data=b"", dlc=r.choice((0, len(m.data), 8)), is_remote_frame=True)


def _error(m, r, ids):
    return _copy(m, is_error_frame=True)


def _extended(m, r, ids):
    i = m.arbitration_id if r.random() < 0.5 else r.getrandbits(29)
    return _copy(m, arbitration_id=i, is_extended_id=True)


def _neighbour_id(m, r, ids):
    return _copy(m, arbitration_id=(m.arbitration_id + r.choice((-1, 1, 16, -16))) & 0x7FF)


def _foreign_id(m, r, ids):
    return _copy(m, arbitration_id=r.choice(ids))      # a payload under another frame's layout


def _counter(m, r, ids):
    if not m.data:
        return m
    data = bytearray(m.data)
    # mostly near misses (duplicates, reordering); a far jump makes the genuine samples after it
    # look late for up to 128 cycles, so it is kept rare to leave the decoders work to do
    step = r.getrandbits(8) if r.random() < 0.05 else r.choice((-2, -1, 1, 2))
    data[0] = (data[0] + step) & 0xFF
    return _copy(m, data=bytes(data))


MUTATIONS = {f.__name__.lstrip("_"): f for f in (_flip_bits, _truncate, _extend, _dlc_mismatch, _fd, _remote,
                                                _error, _extended, _neighbour_id, _foreign_id, _counter)}
_MUT = tuple(MUTATIONS.items())


def random_frame(r: random.Random) -> can.Message:
    ext = r.random() < 0.2
    fd = r.random() < 0.2
    n = r.choice(FD_LENGTHS) if fd else r.randint(0, 8)
    remote = not fd and r.random() < 0.05
    return can.Message(arbitration_id=r.getrandbits(29 if ext else 11), data=b"" if remote else r.randbytes(n),
                       dlc=n if r.random() < 0.9 else r.randint(0, 15), is_extended_id=ext, is_fd=fd,
                       bitrate_switch=fd and r.random() < 0.5, is_remote_frame=remote,
                       is_error_frame=r.random() < 0.03, check=False)


# --- the campaign ----------------------------------------------------------------------------

def _sample_ok(s) -> bool:
    """Invariants every decoded sample must hold, whatever the bytes were."""
    if not 0 <= getattr(s, "counter", 0) <= 255:
        return False
    for f in fields(s):
        v = getattr(s, f.name)
        vals = v if isinstance(v, tuple) else (v,)
        if any(isinstance(x, float) and not math.isfinite(x) for x in vals):
            return False
    return True


def fuzz(wire_map: wire.WireMap, n_frames: int, seed: int = 0, fd: bool = False) -> Report:
    """Feed ``n_frames`` frames, spread over the buses of ``wire_map``, through every listener."""
    r = random.Random(seed)
    rep = Report()
    kinds = [k for k, w in MIX for _ in range(w)]
    rigs = []
    for spec in wire_map.buses.values():
        out: list = []
        monitor, drivers = devices.listeners_for(spec, out.append, fd=fd)
        stream = valid_stream(spec, r)
        rigs.append((spec, [monitor, *drivers], out, stream, sorted(spec.ids), [0]))

    def sink_check(out):
        for s in out:
            if not isinstance(s, SAMPLE_TYPES) or not _sample_ok(s):
                rep.bad_samples += 1
        rep.samples += len(out)
        out.clear()

    t0 = time.perf_counter()
    for i in range(n_frames):
        spec, listeners, out, stream, ids, cursor = rigs[i % len(rigs)]
        kind = kinds[r.randrange(len(kinds))]
        if kind == "random":
            msg = random_frame(r)
        else:
            # a mutated frame replaces the next valid one, so it meets assemblies in progress
            msg = stream[cursor[0]]
            cursor[0] = (cursor[0] + 1) % len(stream)
            if kind == "mutated":
                for _ in range(r.choice((1, 1, 1, 2, 3))):
                    name, mutate = _MUT[r.randrange(len(_MUT))]
                    msg = mutate(msg, r, ids)
                    rep.mutations[name] += 1
        rep.kinds[kind] += 1
        for lst in listeners:
            try:
                lst.on_message_received(msg)
            except Exception as exc:  # noqa: BLE001 - counting is the point: this must never happen
                key = f"{type(lst).__name__}: {type(exc).__name__}"
                rep.exceptions[key] += 1
                if not rep.first_failure:
                    rep.first_failure = f"{key}: {exc} <- {msg!r} data={bytes(msg.data).hex()} dlc={msg.dlc}"
        if len(out) > 256:
            sink_check(out)
    rep.seconds = time.perf_counter() - t0
    rep.frames = n_frames
    for _, listeners, out, _, _, _ in rigs:
        sink_check(out)
        for lst in listeners:
            if isinstance(lst, devices.BusMonitor):
                rep.rejected.update({f"bus/{k}": v for k, v in lst.counters.rejected.items()})
            else:
                for c in lst.counters():
                    rep.rejected.update({f"device/{k}": v for k, v in c.rejected.items()})
                    rep.lost += c.lost
    return rep


def wire_map_for(robot: str) -> wire.WireMap:
    import robot_description

    return wire.WireMap.from_robot(robot_description.load(robot))


def figures(quick: bool = False, frames: int | None = None) -> list[dict]:
    """The suite's rows (``python -m benchmarks --fuzz``): 1 M frames (100 k with ``quick``)
    through every listener of paper_robot, beside cantools' per-frame decode."""
    from benchmarks.anchors import ratio, row

    n = frames or (100_000 if quick else 1_000_000)
    rep = fuzz(wire_map_for("paper_robot"), n, seed=1)
    n_exc = sum(rep.exceptions.values())
    return [
        row("fuzz: random + mutated frames through every listener", rep.frames_per_s, "frames/s",
            anchor="cantools_decode", ratio=ratio(rep.frames_per_s, "cantools_decode"),
            note=f"{rep.frames} frames, seed 1, {rep.samples} samples accepted, "
                 f"{sum(rep.rejected.values())} rejections counted"),
        row("fuzz: exceptions out of a driver", n_exc, "count", target="0", ok=n_exc == 0,
            note=rep.first_failure or None),
        row("fuzz: decoded samples breaking an invariant", rep.bad_samples, "count", target="0",
            ok=rep.bad_samples == 0),
    ]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.fuzz_drivers", description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=1_000_000, help="frames to feed (default 1000000)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--robot", default="paper_robot", help="robot description name or URDF path")
    p.add_argument("--fd", action="store_true", help="drivers configured for CAN FD")
    a = p.parse_args(argv)
    wm = wire_map_for(a.robot)
    rep = fuzz(wm, a.frames, a.seed, a.fd)
    print(f"robot {wm.robot} ({len(wm.buses)} buses), seed {a.seed}, fd={a.fd}")
    print(f"frames      {rep.frames}  ({', '.join(f'{k} {v}' for k, v in sorted(rep.kinds.items()))})")
    print(f"throughput  {rep.frames_per_s:,.0f} frames/s through every listener ({rep.seconds:.1f} s)")
    print(f"samples     {rep.samples} accepted, {rep.bad_samples} breaking an invariant; "
          f"lost (counter gaps) {rep.lost}")
    print(f"exceptions  {sum(rep.exceptions.values())}" + (f"  {dict(rep.exceptions)}" if rep.exceptions else ""))
    if rep.first_failure:
        print(f"first       {rep.first_failure}")
    print("rejections by reason:")
    for k, v in sorted(rep.rejected.items(), key=lambda kv: -kv[1]):
        print(f"  {k:<22} {v:>10}")
    print("mutations applied: " + ", ".join(f"{k} {v}" for k, v in sorted(rep.mutations.items())))
    return 1 if rep.exceptions or rep.bad_samples else 0


if __name__ == "__main__":
    sys.exit(main())
