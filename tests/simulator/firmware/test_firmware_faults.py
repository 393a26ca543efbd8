"""Fault injection: what the firmware says it injected is exactly what the drivers' health
counts (the relation of docs/firmware.md, restated here), lockstep determinism, knob checks."""
from __future__ import annotations

import pytest

from firmware_rig import Rig, by_device, snapshot
from simulator import firmware, scenario
from simulator.engine import Simulation

DURATION_S = 1.5


@pytest.fixture(scope="module")
def run():
    """One simulated run of the capture scenario: (robot, readings of every step)."""
    sim = Simulation(scenario.load("capture", {"duration_s": DURATION_S}))
    readings = [snapshot(sim.step()) for _ in range(sim.n_steps)]
    return sim.robot, readings


def _feed(robot, readings, faults, fd=False, on_step=None, sent=None):
    fw = firmware.Firmware(robot, fd=fd, faults=faults)
    rig = Rig(robot, fd=fd)
    for r in readings:
        batch = fw.frames(r)
        rig.feed(batch)
        if sent is not None:
            sent += batch
        if on_step:
            on_step(r, rig)
    rig.feed(fw.flush())
    return fw, rig


def _expected(c, multi: bool) -> dict:
    """docs/firmware.md, 'How each fault shows up'."""
    return {"samples": c["samples"] - c["drop"] - c["bad_dlc"] - c["silent"] - c["reorder"],
            "lost": c["drop"] + c["bad_dlc"] + c["reorder"] + c["silent"] + c["jump"],
            "late": c["reorder"], "duplicate": c["duplicate"] - c["duplicate_last"],
            "incomplete": c["drop"] + c["bad_dlc"] + c["duplicate_last"] if multi else 0,
            "dlc": c["bad_dlc"]}


MULTI = {"imu", "thrusters", "arm0", "arm1"}


@pytest.mark.parametrize("fd", [False, True], ids=["classic", "fd"])
def test_random_faults_are_counted_exactly(run, fd):
    robot, readings = run
    faults = firmware.Faults(drop_rate=0.03, duplicate_rate=0.03, reorder_rate=0.03, bad_dlc_rate=0.03,
                             seed=11, from_s=0.1, until_s=DURATION_S - 0.2)
    fw, rig = _feed(robot, readings, faults, fd=fd)
    health = rig.health(readings[-1].t_ns)
    totals = dict.fromkeys(firmware.COUNT_KEYS, 0)
    for dev in fw.devices:
        c = fw.counts[dev]
        h = health[dev]
        rej = dict(h.rejected)
        got = {"samples": h.samples, "lost": h.lost, "late": rej.get("late", 0),
               "duplicate": rej.get("duplicate", 0), "incomplete": rej.get("incomplete", 0),
               "dlc": rej.get("dlc", 0)}
        assert got == _expected(c, dev in MULTI), f"{dev}: injected {dict(c)}"
        assert set(rej) <= {"late", "duplicate", "incomplete", "dlc"}, f"{dev}: {rej}"
        assert fw.expected_health(dev) == got
        for k in totals:
            totals[k] += c[k]
    # not vacuous: every kind happened, including a duplicated completing part
    for k in ("drop", "duplicate", "duplicate_last", "reorder", "bad_dlc"):
        assert totals[k] > 5, totals
    # every sample that was decoded is a distinct counter, in order (late ones were dropped)
    for dev, samples in by_device(rig.samples).items():
        ctrs = [s.counter for s in samples]
        assert all((b - a) & 0xFF in range(1, 128) for a, b in zip(ctrs, ctrs[1:])), dev
    for bus, h in rig.bus_health(readings[-1].t_ns).items():
        assert h.frames == fw.frames_sent[bus] and h.rejected == ()


def test_corrupted_bytes_change_exactly_the_hit_samples(run):
    robot, readings = run
    _, clean = _feed(robot, readings, None)
    fw, bad = _feed(robot, readings, firmware.Faults(corrupt_rate=0.05, seed=3))
    a, b = by_device(clean.samples), by_device(bad.samples)
    assert a.keys() == b.keys()
    for dev, samples in a.items():
        name = dev[1].rsplit("/", 1)[0] + "/torque_cmd" if isinstance(dev, tuple) else dev
        changed = sum(x != y for x, y in zip(samples, b[dev]))
        assert len(samples) == len(b[dev])
        if not isinstance(dev, tuple):
            assert changed == fw.counts[name]["corrupt"], dev
        assert changed <= fw.counts[name]["corrupt"]
    # invisible to the counters (no CRC in the payload): nothing rejected, nothing lost
    assert all(h.lost == 0 and h.rejected == () for h in bad.health(readings[-1].t_ns).values())
    assert sum(fw.counts[d]["corrupt"] for d in fw.devices) > 20


def test_silent_device_goes_stale_and_its_samples_count_as_lost(run):
    robot, readings = run
    # gaps under 128 samples: an 8-bit counter cannot tell a longer one from a late sample
    faults = firmware.Faults(silent=(("arm0", 0.3, 0.1), ("imu", 0.6, 0.2), ("arm1/j2", 0.1, 0.05)))
    seen, sent = {}, []

    def probe(r, rig):
        if r.t_ns in (350_000_000, 650_000_000, 1_000_000_000):
            seen[r.t_ns] = rig.health(r.t_ns)

    fw, rig = _feed(robot, readings, faults, on_step=probe, sent=sent)
    stale = {t: sorted(d for d, h in hs.items() if h.stale) for t, hs in seen.items()}
    assert stale == {350_000_000: ["arm0"], 650_000_000: ["imu"], 1_000_000_000: []}
    health = rig.health(readings[-1].t_ns)
    assert fw.counts["arm0"]["silent"] == 100 and health["arm0"].lost == 100
    assert fw.counts["imu"]["silent"] == 100 and health["imu"].lost == 100
    assert fw.counts["arm1/j2"]["silent"] == 50 and health["arm1/j2"].lost == 50
    assert health["arm0/j1"].lost == 0
    assert all(h.rejected == () for h in health.values())
    # the silent node's heartbeat is missing too: FT (0x701 on arm0) skips its 0.3 s beat
    beats = [m.timestamp for b, m in sent if b == "arm0" and m.arbitration_id == 0x701]
    assert len(beats) == 14 and 0.3 not in beats


def test_counter_jumps_count_as_lost(run):
    robot, readings = run
    faults = firmware.Faults(counter_jumps=(("arm0/j1", 0.2, 5), ("thrusters", 0.5, 3), ("arm1", 0.7, 126)))
    fw, rig = _feed(robot, readings, faults)
    health = rig.health(readings[-1].t_ns)
    assert (health["arm0/j1"].lost, health["thrusters"].lost, health["arm1"].lost) == (5, 3, 126)
    assert (fw.counts["arm0/j1"]["jump"], fw.counts["thrusters"]["jump"], fw.counts["arm1"]["jump"]) == (5, 3, 126)
    assert all(h.rejected == () for h in health.values())


def _frames(seed: int, duration_s: float = 0.3):
    sim = Simulation(scenario.load("capture", {"duration_s": duration_s}))
    fw = firmware.Firmware(sim.robot, faults=firmware.Faults(drop_rate=0.05, duplicate_rate=0.05, reorder_rate=0.05,
                                                             corrupt_rate=0.05, bad_dlc_rate=0.05, seed=seed))
    out = []
    while sim.k < sim.n_steps:
        out += fw.frames(sim.step())
    out += fw.flush()
    return [(b, m.arbitration_id, bytes(m.data), m.dlc, m.is_fd, m.timestamp) for b, m in out]


def test_lockstep_is_deterministic():
    a, b = _frames(5), _frames(5)
    assert len(a) > 3000 and a == b
    assert _frames(6) != a            # the seed matters, so the equality above means something


def test_fault_knobs_are_checked():
    with pytest.raises(firmware.FirmwareError, match="probability"):
        firmware.Faults(drop_rate=1.5)
    with pytest.raises(firmware.FirmwareError, match="sum"):
        firmware.Faults(drop_rate=0.6, duplicate_rate=0.6)
    with pytest.raises(firmware.FirmwareError, match="jump"):
        firmware.Faults(counter_jumps=(("imu", 0.1, 200),))
    with pytest.raises(firmware.FirmwareError, match="unknown key"):
        firmware.Faults.from_table({"drop": 0.1})
    f = firmware.Faults.from_table({"drop_rate": 0.1, "silent": [["imu", 0.5, 0.1]]})
    assert f.silent == (("imu", 0.5, 0.1),) and f.drop_rate == 0.1 and f.any
    import robot_description
    with pytest.raises(firmware.FirmwareError, match="no device 'arm9'"):
        firmware.Firmware(robot_description.load("paper_robot"), faults=firmware.Faults(silent=(("arm9", 0, 1),)))
