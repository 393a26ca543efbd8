"""Adapters: what reaches a python-can bus constructor from ``-b/--bitrate``, ``--data-bitrate``,
``--bus-kwarg`` and python-can's own configuration, on every command that opens a bus.

The bus is a fake interface registered the way python-can plugins are (a distribution with a
``can.interface`` entry point), in a subprocess whose path holds it; each construction writes
its arguments as one JSON line.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from gateway.cli import main

REPO = Path(__file__).resolve().parents[2]

PLUGIN = '''
import json, os, time
import can

class FakeBus(can.BusABC):
    def __init__(self, channel=None, **kwargs):
        with open(os.environ["FAKECAN_OUT"], "a") as f:
            f.write(json.dumps({"channel": channel, **{k: v if isinstance(v, (int, float, str, bool, type(None)))
                                                       else repr(v) for k, v in kwargs.items()}}) + "\\n")
        self.channel_info = f"fake {channel}"
        super().__init__(channel=channel, **kwargs)

    def send(self, msg, timeout=None):
        pass

    def _recv_internal(self, timeout):
        time.sleep(min(timeout if timeout is not None else 0.01, 0.01))
        return None, False
'''


@pytest.fixture(scope="module")
def plugin(tmp_path_factory) -> Path:
    """A folder with the ``fakecan`` interface as an installed python-can plugin."""
    root = tmp_path_factory.mktemp("plugin")
    (root / "fakecan_plugin.py").write_text(PLUGIN)
    dist = root / "fakecan_plugin-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: fakecan-plugin\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[can.interface]\nfakecan = fakecan_plugin:FakeBus\n")
    return root


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    """A short session MCAP with raw frames on every bus (what bsc replay puts back on CAN)."""
    import can

    path = tmp_path_factory.mktemp("session") / "robot.log"
    lines = [f"({1767225600 + k / 1000:.6f}) {bus} 300#0000000000000000"
             for k in range(20) for bus in ("arm0", "arm1", "spacecraft")]
    path.write_text("\n".join(lines) + "\n")
    out = path.with_suffix(".mcap")
    assert main(["import", str(path), "--robot", "paper_robot", "-o", str(out)]) == 0
    assert len(list(can.LogReader(path))) == 60
    return out


def bsc(plugin: Path, tmp_path: Path, *args: str, env: dict | None = None) -> tuple[subprocess.CompletedProcess, list]:
    """``bsc ARGS`` with the plugin installed, ``tmp_path`` its home (where python-can looks for
    ``~/.canrc``); returns the process and the constructor calls."""
    out = tmp_path / "calls.jsonl"
    out.unlink(missing_ok=True)
    e = {k: v for k, v in os.environ.items() if not k.startswith("CAN_")}
    e.update(OPENBLAS_NUM_THREADS="1", FAKECAN_OUT=str(out), HOME=str(tmp_path),
             PYTHONPATH=os.pathsep.join([str(plugin), str(REPO)]), **(env or {}))
    proc = subprocess.run([sys.executable, "-m", "gateway.cli", *args], capture_output=True, text=True,
                          cwd=tmp_path, env=e, timeout=120)
    calls = [json.loads(x) for x in out.read_text().splitlines()] if out.exists() else []
    return proc, calls


def replay_args(session: Path, *extra: str) -> list[str]:
    return ["replay", str(session), "-i", "fakecan", "-c", "arm0=pcan-usb1", "-c", "spacecraft=pcan-usb2",
            "--rate", "0", "-q", *extra]


def test_default_is_the_dbc_bitrate(plugin, session, tmp_path):
    proc, calls = bsc(plugin, tmp_path, *replay_args(session))
    assert proc.returncode == 0, proc.stderr
    assert [(c["channel"], c["bitrate"]) for c in calls] == [("pcan-usb1", 1_000_000), ("pcan-usb2", 1_000_000)]
    assert not any("data_bitrate" in c for c in calls) and "sent frames 40" in proc.stdout


def test_flags_reach_the_constructor(plugin, session, tmp_path):
    proc, calls = bsc(plugin, tmp_path, *replay_args(session, "-b", "500k", "--bus-kwarg", "serial=0x1234",
                                                      "--bus-kwarg", "app_name=CANalyzer", "--bus-kwarg",
                                                      "receive_own_messages=true"))
    assert proc.returncode == 0, proc.stderr
    for c in calls:
        assert (c["bitrate"], c["serial"], c["app_name"], c["receive_own_messages"]) == (500_000, 0x1234,
                                                                                           "CANalyzer", True)
    proc, calls = bsc(plugin, tmp_path, *replay_args(session, "--fd", "--data-bitrate", "2M"))
    assert proc.returncode == 0, proc.stderr
    assert all((c["fd"], c["bitrate"], c["data_bitrate"]) == (True, 1_000_000, 2_000_000) for c in calls)
    proc, calls = bsc(plugin, tmp_path, *replay_args(session, "--fd"))
    assert all(c["data_bitrate"] == 5_000_000 for c in calls)


def test_python_can_configuration_is_honoured_unless_a_flag_overrides_it(plugin, session, tmp_path):
    (tmp_path / ".canrc").write_text("[default]\nbitrate = 250000\nserial = 77\n\n"
                                      "[lab]\nbitrate = 125000\n")
    proc, calls = bsc(plugin, tmp_path, *replay_args(session))
    assert proc.returncode == 0, proc.stderr
    assert all((c["bitrate"], c["serial"]) == (250_000, 77) for c in calls)
    proc, calls = bsc(plugin, tmp_path, *replay_args(session, "--bus-kwarg", "config_context=lab"))
    assert all(c["bitrate"] == 125_000 for c in calls)
    proc, calls = bsc(plugin, tmp_path, *replay_args(session), env={"CAN_BITRATE": "800000"})
    assert all(c["bitrate"] == 800_000 for c in calls)          # the environment over the file
    proc, calls = bsc(plugin, tmp_path, *replay_args(session, "-b", "1M", "--bus-kwarg", "serial=5"),
                      env={"CAN_BITRATE": "800000"})
    assert all((c["bitrate"], c["serial"]) == (1_000_000, 5) for c in calls)
    # a bit timing configured instead of a bit rate: no bit rate added
    (tmp_path / ".canrc").write_text("[default]\nf_clock = 80000000\nbrp = 10\ntseg1 = 5\ntseg2 = 2\nsjw = 1\n"
                                     "nof_samples = 1\n")
    proc, calls = bsc(plugin, tmp_path, *replay_args(session))
    assert proc.returncode == 0, proc.stderr
    assert all("bitrate" not in c and "BitTiming" in c["timing"] for c in calls)


def test_every_command_that_opens_a_bus_takes_the_flags(plugin, session, tmp_path):
    proc, calls = bsc(plugin, tmp_path, "sim", "--duration", "0.05", "--out", str(tmp_path / "sim"), "--no-plots",
                      "--no-compare", "--quiet", "-i", "fakecan", "-c", "bsc", "-b", "250k",
                      "--bus-kwarg", "serial=9")
    assert proc.returncode == 0, proc.stderr
    assert [(c["channel"], c["bitrate"], c["serial"]) for c in calls] == [
        ("bsc-arm0", 250_000, 9), ("bsc-arm1", 250_000, 9), ("bsc-spacecraft", 250_000, 9)]
    proc, calls = bsc(plugin, tmp_path, "record", "-o", str(tmp_path / "r.mcap"), "--no-zenoh", "-i", "fakecan",
                      "-c", "bsc", "--duration", "0.2", "-b", "500k")
    assert proc.returncode == 0, proc.stderr
    assert [(c["channel"], c["bitrate"]) for c in calls] == [
        ("bsc-arm0", 500_000), ("bsc-arm1", 500_000), ("bsc-spacecraft", 500_000)]
    from gateway.log.context import read_context

    assert read_context(tmp_path / "r.mcap").session["bus_rates"] == "bitrate 500000"   # the log says
    from drivers.canbus import BusOptions
    from gateway.cli import build_parser

    argv = ["gateway", "-i", "pcan", "-c", "bsc", "-b", "1M", "--data-bitrate", "8M", "--fd", "--bus-kwarg", "x=1"]
    args = build_parser(argv).parse_args(argv)
    assert BusOptions.from_args(args) == BusOptions(1_000_000, 8_000_000, (("x", 1),))


@pytest.mark.parametrize("args, words", [
    (["--data-bitrate", "2M"], "must run CAN FD [--fd]"),
    (["-b", "fast"], "a bit rate such as"),
    (["--bus-kwarg", "serial"], "KEY=VALUE"),
    (["--bus-kwarg", "channel=can0"], "--interface/--channel"),
])
def test_bad_bus_flags_are_one_line(plugin, session, tmp_path, args, words):
    proc, calls = bsc(plugin, tmp_path, *replay_args(session, *args))
    assert proc.returncode == 2 and words in proc.stderr and "Traceback" not in proc.stderr
    assert calls == []


def test_bus_flags_need_a_bus(session, tmp_path, capsys):
    assert main(["record", "-o", str(tmp_path / "x.mcap"), "-b", "500k"]) == 2
    assert "give --interface" in capsys.readouterr().err
    assert main(["sim", "--duration", "0.05", "--out", str(tmp_path / "s"), "-b", "500k"]) == 2


def test_gateway_opens_its_buses_with_the_flags_and_says_so(plugin, tmp_path):
    from support import free_port

    proc, calls = bsc(plugin, tmp_path, "gateway", "-i", "fakecan", "-c", "bsc", "-b", "500k",
                      "--bus-kwarg", "serial=3", "--robot", "paper_robot", "--listen",
                      f"tcp/127.0.0.1:{free_port()}", "--duration", "0.3", "--record", str(tmp_path / "g.mcap"))
    assert proc.returncode == 0, proc.stderr
    assert [(c["channel"], c["bitrate"], c["serial"]) for c in calls] == [
        ("bsc-arm0", 500_000, 3), ("bsc-arm1", 500_000, 3), ("bsc-spacecraft", 500_000, 3)]
    assert "(receive: threads); bitrate 500000" in proc.stdout
    from gateway.log.context import read_context

    assert read_context(tmp_path / "g.mcap").session["bus_rates"] == "bitrate 500000"
