"""CAN logs of other tools: ``bsc import``, ``bsc replay LOG``, ``bsc export``, and bad logs.

The logs are what a real robot's tools write: the simulated robot's firmware frames, stamped to
the microsecond at epoch times (each bus a little apart, as adapters stamp them), in the order
they came, written by python-can's own writers.
"""
from __future__ import annotations

import gzip
import json
from pathlib import Path

import can
import pytest

from gateway import keys
from gateway.log import context, reader
from gateway.cli import main
from gateway.log import canlog
from gateway.log.recorder import Recorder

EPOCH_NS = 1_767_225_600_000_000_000     # 2026-01-01: a real log's clock
CHANNELS = {"arm0": "can0", "arm1": "can1", "spacecraft": "can2"}
MAP = [a for b, c in CHANNELS.items() for a in ("--bus", f"{b}={c}")]


def sim_frames(seconds: float = 0.3):
    """``(bus, can.Message)`` of the capture scenario's firmware, in send order, stamped like a
    SocketCAN log (us): bus k's frames of a step 40*k us after the arm0's, 1 us apart."""
    from simulator import scenario
    from simulator.engine import Simulation
    from simulator.firmware import Firmware

    sim = Simulation(scenario.load("capture", {"duration_s": seconds}))
    fw = Firmware(sim.robot)
    out, buses = [], list(CHANNELS)
    while sim.k < sim.n_steps:
        n = dict.fromkeys(buses, 0)
        for bus, msg in fw.frames(sim.step()):
            us = (EPOCH_NS + int(msg.timestamp * 1e9)) // 1000 + 40 * buses.index(bus) + n[bus]
            n[bus] += 1
            msg.timestamp = us / 1e6
            out.append((bus, msg))
    return out


@pytest.fixture(scope="module")
def candump(tmp_path_factory) -> Path:
    """A ``candump -L`` log of the simulated robot on can0..can2."""
    path = tmp_path_factory.mktemp("logs") / "robot.log"
    with path.open("w") as f:                  # as candump -L writes it (python-can's writer clamps times)
        for bus, m in sim_frames():
            f.write(f"({m.timestamp:.6f}) {CHANNELS[bus]} {m.arbitration_id:03X}#{bytes(m.data).hex().upper()}\n")
    return path


def efforts(path: Path) -> dict[str, list[tuple[int, bytes]]]:
    """Every effort message (log time, bytes) of a replay output, by topic, in file order."""
    out: dict[str, list] = {}
    for topic, _, m in reader.iter_file_order(path, lambda t, s: "/efforts/" in t):
        out.setdefault(topic, []).append((m.log_time, bytes(m.data)))
    return out


def replay(tmp_path: Path, name: str, *args: str) -> tuple[dict, dict]:
    out = tmp_path / name
    assert main(["replay", *map(str, args), "-o", str(out), "-q"]) == 0
    return efforts(out / "replay.mcap"), json.loads((out / "report.json").read_text())


@pytest.fixture(scope="module")
def session(candump, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("session") / "session.mcap"
    assert main(["import", str(candump), "--robot", "paper_robot", *MAP, "-o", str(path)]) == 0
    return path


def test_import_writes_a_session_every_tool_takes(candump, session, tmp_path, capsys):
    ctx = context.read_context(session)
    assert ctx.buses == list(CHANNELS) and ctx.robot_name == "paper_robot" and ctx.urdf_text
    assert ctx.session["imported_from"] == "robot.log"
    assert main(["info", str(session)]) == 0
    assert "/can/spacecraft" in capsys.readouterr().out
    # replaying the log directly = replaying its import; the good estimates are there
    direct, report = replay(tmp_path, "direct", candump, "--robot", "paper_robot", *MAP)
    imported, _ = replay(tmp_path, "imported", session)
    assert direct == imported
    assert report["source"] == str(candump) and report["import"]["frames_written"] == report["frames_in"]
    assert report["good_efforts"] > 0.9 * report["efforts"] > 0
    # the log's order and times: the frames are the file's, one for one
    frames = [(b, t, m.arbitration_id, bytes(m.data)) for b, t, m in reader.iter_can_frames(session)]
    stats = canlog.ImportStats("", "")
    logged = [(b, t, m.arbitration_id, bytes(m.data))
              for b, t, m in canlog.import_frames(candump, list(CHANNELS), dict(CHANNELS), stats)]
    assert frames == logged and frames[0][1] % 1000 == 0 and frames[0][1] >= EPOCH_NS


@pytest.mark.parametrize("name", ["x.log", "x.asc", "x.blf", "x.trc", "x.log.gz", "x.asc.gz", "x.blf.gz"])
def test_export_then_import_gives_the_efforts_of_the_session(session, tmp_path, name, capsys):
    reference, _ = replay(tmp_path, "ref", session)
    out = tmp_path / name
    if name == "x.blf.gz":                     # python-can writes no .blf.gz, and reads it
        assert main(["export", str(session), "-o", str(out)]) == 2
        assert main(["export", str(session), "-o", str(tmp_path / "x.blf")]) == 0
        out.write_bytes(gzip.compress((tmp_path / "x.blf").read_bytes()))
    else:
        assert main(["export", str(session), "-o", str(out)]) == 0
    said = capsys.readouterr().out
    back = said.rsplit("read it back with ", 1)[1].split()
    got, report = replay(tmp_path, "back", out, "--robot", "paper_robot", *back)
    assert got == reference
    assert report["import"]["unmapped"] == {} and report["import"]["ended_early"] is None


def test_csv_holds_one_bus(session, tmp_path, capsys):
    out = tmp_path / "arm1.csv"
    assert main(["export", str(session), "-o", str(out)]) == 2
    assert "CSV" in capsys.readouterr().err
    assert main(["export", str(session), "-o", str(out), "--bus", "arm1=-"]) == 0
    reference, _ = replay(tmp_path, "ref", session, "--topic", "/can/arm1")
    got, _ = replay(tmp_path, "back", out, "--robot", "paper_robot", "--bus", "arm1=-")
    assert got == reference


def test_export_channels_and_names(session, tmp_path, capsys):
    out = tmp_path / "two.log"
    assert main(["export", str(session), "-o", str(out), "--bus", "arm0=vcan3", "--bus", "spacecraft=vcan9"]) == 0
    chans = {m.channel for m in can.LogReader(out)}
    assert chans == {"vcan3", "vcan9"}
    assert main(["export", str(session), "-o", str(out)]) == 2          # exists
    assert "--force" in capsys.readouterr().err
    assert main(["export", str(session), "-o", str(tmp_path / "x.txt")]) == 2
    assert main(["export", str(session), "-o", str(tmp_path / "x.asc"), "--bus", "arm0=can0"]) == 2
    assert "numbers from 1" in capsys.readouterr().err


def test_a_log_needs_a_robot_and_a_mapping_and_says_what_it_holds(candump, tmp_path, capsys):
    out = str(tmp_path / "r")
    assert main(["replay", str(candump), "-o", out]) == 2
    assert "--robot" in capsys.readouterr().err
    assert main(["replay", str(candump), "-o", out, "--robot", "paper_robot"]) == 2
    err = capsys.readouterr().err
    assert "channels found: can0 (" in err and "can2 (" in err and "map them with arm0=CHANNEL" in err
    assert err.rstrip().endswith("[--bus]")
    assert err.count("\n") == 1
    assert main(["replay", str(candump), "-o", out, "--robot", "paper_robot", "--bus", "arm0=can7"]) == 2
    err = capsys.readouterr().err
    assert "arm0=can7: no such channel" in err and "can1 (" in err
    assert main(["replay", str(candump), "-o", out, "--robot", "paper_robot", "--bus", "arm9=can0"]) == 2
    assert "buses arm0, arm1, spacecraft" in capsys.readouterr().err
    assert main(["import", str(candump), "--robot", "paper_robot", "-o", str(tmp_path / "s.mcap")]) == 2
    assert not (tmp_path / "s.mcap").exists()
    capsys.readouterr()
    assert main(["replay", str(candump), "--robot", "paper_robot", *MAP]) == 2          # no mode
    assert "choose one mode" in capsys.readouterr().err
    assert main(["replay", str(candump), "--robot", "paper_robot", *MAP, "--zenoh"]) == 2
    assert "raw frames only" in capsys.readouterr().err


def test_a_channel_mapped_to_no_bus_is_counted(candump, tmp_path, capsys):
    _, report = replay(tmp_path, "two", candump, "--robot", "paper_robot", "--bus", "arm0=can0", "--bus", "arm1=can1")
    assert report["import"]["unmapped"] == {"can2": report["import"]["by_channel"]["can2"]}
    err = capsys.readouterr().err
    assert "left out (channel maps to no bus): channel can2" in err
    # the robot's bus that got nothing is named, with what it means and how to map it
    assert report["import"]["unfed"] == ["spacecraft"]
    assert ("no channel maps to the robot's bus spacecraft: its devices get no frame and no effort can be good "
            "(map it: spacecraft=CHANNEL; channels found: can0") in err
    assert report["good_efforts"] == 0


def write_bad_log(path: Path) -> dict:
    """A candump log with what a real bus and a real logger give besides good frames."""
    lines = []
    t = EPOCH_NS // 1000
    for k in range(200):
        lines.append(f"({(t + 1000 * k) / 1e6:.6f}) can0 7A5#0102030405060708")      # unknown id
    lines.append(f"({t / 1e6:.6f}) can0 7A5#01")                                       # back in time
    lines.append(f"({(t + 500) / 1e6:.6f}) can0 20000080#0000000000000000")            # error frame
    lines.append(f"({(t + 600) / 1e6:.6f}) can0 300#R")                                # remote frame
    lines.append(f"({(t + 700) / 1e6:.6f}) can3 300#0011")                            # no bus
    path.write_text("\n".join(lines) + "\n")
    return {"unknown": 201}


def test_bad_frames_are_counted_never_good(tmp_path, capsys):
    log = tmp_path / "bad.log"
    write_bad_log(log)
    _, report = replay(tmp_path, "bad", log, "--robot", "paper_robot", "--bus", "arm0=can0")
    err = capsys.readouterr().err
    imp = report["import"]
    assert imp["backwards"] == {"arm0": 1} and imp["unmapped"] == {"can3": 1}
    assert imp["error_frames"] == 1 and imp["remote_frames"] == 1
    assert "backwards" in err and "Traceback" not in err
    assert report["rejections"].get("unknown_id", 0) + report["rejections"].get("remote_frame", 0) >= 202
    assert report["rejections"]["error_frame"] == 1          # on its bus (python-can reads it without)
    assert report["good_efforts"] == 0


def test_a_truncated_blf_keeps_what_it_holds(session, tmp_path, capsys):
    blf = tmp_path / "x.blf"
    assert main(["export", str(session), "-o", str(blf)]) == 0
    capsys.readouterr()
    data = blf.read_bytes()
    cut = tmp_path / "cut.blf"
    cut.write_bytes(data[:len(data) * 2 // 3])
    args = ["--robot", "paper_robot", "--bus", "arm0=1", "--bus", "arm1=2", "--bus", "spacecraft=3"]
    got, report = replay(tmp_path, "cut", cut, *args)
    err = capsys.readouterr().err
    assert "Traceback" not in err and "the file ends early (truncated" in err
    assert "truncated" in report["import"]["ended_early"]
    total = sum(1 for _ in reader.iter_can_frames(session))
    assert 0 < report["frames_in"] == report["import"]["frames_read"] < total
    # what it holds is the session's beginning, replayed as the whole session replays it
    whole, _ = replay(tmp_path, "whole", blf, *args)
    for k in whole:
        n = len(got[k])
        same = next((i for i, (a, b) in enumerate(zip(got[k], whole[k])) if a != b), n)
        assert n > 10 and same >= n - 2, (k, n, same)    # the epochs the cut left open differ


@pytest.mark.parametrize("content", [b"", b"this is not a candump log\n", gzip.compress(b"garbage")])
def test_garbage_is_one_line(tmp_path, capsys, content):
    log = tmp_path / ("x.log.gz" if content[:2] == b"\x1f\x8b" else "x.log")
    log.write_bytes(content)
    assert main(["replay", str(log), "-o", str(tmp_path / "r"), "--robot", "paper_robot"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err


def test_an_mcap_named_log_is_an_mcap(tmp_path):
    path = tmp_path / "odd.log"
    with Recorder(path):
        pass
    assert canlog.log_format(path) is None and canlog.log_format(tmp_path / "y.asc.gz") == ".asc"


def test_analyze_takes_logs_and_folders_of_them(candump, session, tmp_path, capsys):
    import argparse

    from gateway.analysis import analyze_session
    from gateway.commands.import_log import analyze_logs

    _, _ = replay(tmp_path, "ref", session)
    ref = analyze_session(tmp_path / "ref" / "replay.mcap").to_json()
    args = argparse.Namespace(robot="paper_robot", bus=MAP[1::2], fd=False)
    work = tmp_path / "work"
    work.mkdir()
    (paths, skipped) = analyze_logs([str(candump)], args, work)
    got = analyze_session(paths[0]).to_json()
    assert skipped == []
    def same(d):                              # NaN (not identifiable) as text: NaN != NaN
        return json.dumps({k: v for k, v in d.items() if k not in ("path", "name", "metadata")}, sort_keys=True)

    a, b = same(got), same(ref)
    assert a == b, [(x, y) for x, y in zip(a.split(","), b.split(",")) if x != y][:5]
    assert got["counts"]["joint_efforts"] > 0
    # a folder: logs in the order of their first frame, whatever their names; a text file
    # named .log that is no CAN log is skipped with its reason
    folder = tmp_path / "logs"
    folder.mkdir()
    late = [ln for ln in candump.read_text().splitlines()]
    shifted = [f"({float(ln[1:ln.index(')')]) + 86400:.6f}){ln[ln.index(')') + 1:]}" for ln in late]
    (folder / "a_late.log").write_text("\n".join(shifted) + "\n")
    (folder / "b_early.log").write_text(candump.read_text())
    (folder / "gateway.log").write_text("INFO started\n")
    capsys.readouterr()
    assert main(["analyze", str(folder), "--robot", "paper_robot", *MAP, "--workers", "1", "--quiet"]) == 0
    out, err = capsys.readouterr()
    assert "2 session(s), in time order: b_early.log .. a_late.log" in out, out
    assert "skipped" in err and "gateway.log" in err


def test_candump_lines_that_are_no_frame_are_skipped_and_counted(candump, tmp_path, capsys):
    lines = candump.read_text().splitlines()
    mid = tmp_path / "mid.log"
    mid.write_text("\n".join(lines[:1000] + ["garbage here", "(1767225600.5) can0 XYZ"] + lines[1000:]) + "\n")
    cut = tmp_path / "cut.log"
    cut.write_text("\n".join(lines[:2000]) + "\n" + lines[2000][:9])          # the logger was killed
    ref, _ = replay(tmp_path, "ref", candump, "--robot", "paper_robot", *MAP)
    got, report = replay(tmp_path, "mid", mid, "--robot", "paper_robot", *MAP)
    assert got == ref and report["import"]["bad_lines"] == 2
    assert report["import"]["first_bad_line"].startswith("line 1001: 'garbage here'")
    _, report = replay(tmp_path, "cut", cut, "--robot", "paper_robot", *MAP)
    assert report["frames_in"] == 2000 and report["import"]["bad_lines"] == 1
    gz = tmp_path / "cut.log.gz"
    gz.write_bytes(gzip.compress(candump.read_bytes())[:20000])
    _, report = replay(tmp_path, "gz", gz, "--robot", "paper_robot", *MAP)
    assert "EOFError" in report["import"]["ended_early"] and 0 < report["frames_in"] < len(lines)
    assert "Traceback" not in capsys.readouterr().err


def test_info_of_a_log_lists_its_channels(candump, tmp_path, capsys):
    bad = tmp_path / "bad.log"
    write_bad_log(bad)
    assert main(["info", str(candump)]) == 0
    out = capsys.readouterr().out
    assert "candump -L" in out and "--bus BUS=CHANNEL" in out and "bad input:   none" in out
    rows = {ln.split()[0]: ln.split()[1:] for ln in out.splitlines() if ln.startswith("  can")}
    counts = canlog.ImportStats("", "")
    for chan, _, msg in canlog.read_log(candump):
        counts.read(chan, msg)
    assert {c: int(r[0]) for c, r in rows.items()} == dict(counts.by_channel)
    assert abs(float(rows["can0"][1]) - 1000 * counts.by_channel["can0"] / 300) < 0.05 * float(rows["can0"][1])
    assert main(["info", str(bad), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["by_channel"] == {"can0": 203, "can3": 1} and doc["backwards"] == {"can0": 1}
    assert (doc["error_frames"], doc["remote_frames"]) == (1, 1)


def test_fd_frames_and_check_of_a_log(candump, tmp_path, capsys):
    fd = tmp_path / "fd.log"
    lines = candump.read_text().splitlines()
    fd.write_text("\n".join(ln.replace("#", "##1", 1) for ln in lines) + "\n")     # the same frames, as FD
    _, report = replay(tmp_path, "classic", fd, "--robot", "paper_robot", *MAP)
    assert "import them as CAN FD" in capsys.readouterr().err and report["import"]["fd_frames"] == len(lines)
    assert report["good_efforts"] == 0 and report["rejections"]["fd_on_classic"] > 0
    _, report = replay(tmp_path, "fd", fd, "--robot", "paper_robot", *MAP, "--fd")
    assert report["good_efforts"] > 0.9 * report["efforts"] > 0
    assert "import them as CAN FD" not in capsys.readouterr().err
    assert main(["replay", str(candump), "--robot", "paper_robot", *MAP, "-o", str(tmp_path / "c"), "--check"]) == 2
    assert "a CAN log holds none" in capsys.readouterr().err


def test_export_a_window_and_ids(session, tmp_path, capsys):
    out = tmp_path / "w.asc"
    assert main(["export", str(session), "-o", str(out), "--start", "0.1", "--duration", "0.05",
                 "--can-id", "0x300,0x301", "-q"]) == 0
    t0 = context.read_context(session).start_ns
    want = [(t, m.arbitration_id) for _, t, m in reader.iter_can_frames(session)
            if t0 + 100_000_000 <= t < t0 + 150_000_000 and m.arbitration_id in (0x300, 0x301)]
    got = [(t, m.arbitration_id) for _, t, m in canlog.read_log(out)]
    assert got == want and len(got) > 50
    before = out.read_bytes()
    assert main(["export", str(session), "-o", str(out), "--start", "50", "--force"]) == 2
    assert "nothing written" in capsys.readouterr().err and out.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["w.asc"]


def test_a_clock_set_mid_log_is_reported_and_replayed(candump, tmp_path, capsys):
    lines = candump.read_text().splitlines()
    early = [f"({float(ln[1:ln.index(')')]) - 1_767_225_000:.6f}){ln[ln.index(')') + 1:]}" for ln in lines[:300]]
    log = tmp_path / "jump.log"
    log.write_text("\n".join(early + lines[300:]) + "\n")      # an RTC set after 300 frames
    ref, _ = replay(tmp_path, "ref", candump, "--robot", "paper_robot", *MAP)
    got, report = replay(tmp_path, "jump", log, "--robot", "paper_robot", *MAP)
    assert report["import"]["jumps"] == {"arm0": 1, "arm1": 1, "spacecraft": 1}
    assert "times jumping ahead" in capsys.readouterr().err
    assert report["good_efforts"] > 0.9 * report["efforts"]
    # after the jump: the clean log's efforts, byte for byte, but for what the joint filter
    # estimates: it started again at the jump (a silence of decades to it), so its full torques
    # and F/T bias converge to the clean log's instead (tests/gateway/estimator/test_joint_filter.py)
    # the thruster filter's per-valve force uncertainty grows over the silence too (its random
    # walk), so the learned valve wrenches' force_sigma_n differ, not the wrenches (those of the
    # same span as the efforts compared)
    since = ref[keys.thruster_effort("paper_robot")][-100][0]
    for k in ref:
        last = sum(t >= since for t, _ in ref[k]) if k.endswith("/efforts/valves") else 100
        assert len(got[k]) >= last >= 5
        for (tg, bg), (tr, br) in zip(got[k][-last:], ref[k][-last:]):
            if k.endswith("/efforts/valves"):
                g, r = json.loads(bg), json.loads(br)
                assert tg == tr and {x: v for x, v in g.items() if x != "force_sigma_n"} == \
                    {x: v for x, v in r.items() if x != "force_sigma_n"}
                continue
            if "/efforts/joints/" not in k:
                assert (tg, bg) == (tr, br)
                continue
            g, r = json.loads(bg), json.loads(br)
            assert tg == tr and len(g["ft_bias"]) == len(r["ft_bias"]) == 6
            assert {x: v for x, v in g.items() if x not in ("full_nm", "ft_bias")} == \
                {x: v for x, v in r.items() if x not in ("full_nm", "ft_bias")}


def test_a_log_goes_back_onto_can(candump, capsys):
    """bsc replay LOG --interface: the log's frames on the robot's buses, each bus in its order."""
    tag = f"canlog-{id(candump)}"
    rx = {b: can.Bus(interface="virtual", channel=f"{tag}-{b}", receive_own_messages=False) for b in CHANNELS}
    try:
        assert main(["replay", str(candump), "--robot", "paper_robot", *MAP, "-i", "virtual", "-c", tag,
                     "--rate", "0", "-q"]) == 0
        stats = canlog.ImportStats("", "")
        want: dict[str, list] = {b: [] for b in CHANNELS}
        for b, _, m in canlog.import_frames(candump, list(CHANNELS), dict(CHANNELS), stats):
            want[b].append((m.arbitration_id, bytes(m.data)))
        for b, bus in rx.items():
            got = []
            while (m := bus.recv(timeout=0)) is not None:
                got.append((m.arbitration_id, bytes(m.data)))
            assert got == want[b], b
    finally:
        for bus in rx.values():
            bus.shutdown()
    assert f"sent frames {stats.frames_written}" in capsys.readouterr().out
