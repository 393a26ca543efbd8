"""The gateway's configuration (gateway/config.py): a TOML file, flags over it, every key documented."""
from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh

from gateway import keys
from gateway.config import DOCS, ConfigError, GatewayConfig, documented_keys
from gateway.zenoh_config import make_config
from support import free_port

ROOT = Path(__file__).resolve().parents[2]


def bsc(*args, cwd=ROOT):
    return subprocess.run([sys.executable, "-m", "gateway.cli", *args], capture_output=True, text=True, cwd=cwd,
                          env=dict(os.environ, OPENBLAS_NUM_THREADS="1"), timeout=120)


def test_every_key_is_documented_and_the_shipped_file_is_the_defaults():
    assert set(documented_keys()) == set(DOCS), set(documented_keys()) ^ set(DOCS)
    shipped = ROOT / "deploy" / "gateway.toml"
    assert shipped.read_text() == GatewayConfig().to_toml(), "regenerate: bsc gateway --print-config > " + str(shipped)
    assert GatewayConfig.load(shipped) == GatewayConfig()


def test_a_file_round_trips_and_relative_paths_are_the_files(tmp_path):
    cfg = GatewayConfig().updated(
        can={"interface": "pcan", "channels": ("arm0=PCAN_USBBUS1", "arm1=PCAN_USBBUS2", "spacecraft=PCAN_USBBUS3"),
             "fd": True, "bitrate": 500_000, "data_bitrate": 2_000_000, "bus_kwargs": (("serial", 1234),
                                                                                      ("app_name", "bsc")),
             "receive": "threads"},
        zenoh={"mode": "client", "connect": ("tcp/127.0.0.1:7447",), "multicast_scouting": True},
        robot={"description": "three_arm", "thrusters": "ring18"},
        service={"health_period_s": 0.25, "publish_samples": False, "max_backlog": 123, "duration_s": 9.5},
        drivers={"source_rate": None, "stale_periods": 4},
        estimator={"max_open": 7, "thrusters": {"gain_sigma": 0.1}, "fdi": {"h_short": 150.0}},
        recording={"path": tmp_path / "s.mcap"})
    f = tmp_path / "gw.toml"
    f.write_text(cfg.to_toml())
    assert GatewayConfig.load(f) == cfg
    assert GatewayConfig.load(f).drivers.timing().rate is None          # "lockstep"
    off = cfg.updated(estimator={"fdi": None})                            # the fault detector off
    f.write_text(off.to_toml())
    assert "fdi = false" in f.read_text() and GatewayConfig.load(f) == off and off.estimator.fdi is None
    f.write_text('[recording]\npath = "logs/s.mcap"\n[zenoh]\nconfig_file = "z.json5"\n')
    loaded = GatewayConfig.load(f)
    assert loaded.recording.path == tmp_path / "logs" / "s.mcap"
    assert loaded.zenoh.config_file == tmp_path / "z.json5"


@pytest.mark.parametrize("text, says", [
    ("[servce]\nretry_s = 1\n", "unknown key servce"),
    ("[service]\nhealth_period = 1\n", "[service]: unknown key health_period"),
    ("[service]\nmax_backlog = 0\n", "max_backlog must be a positive number"),
    ("[service]\npublish_samples = 1\n", "service.publish_samples: expected true or false"),
    ("[can]\nreceive = \"fast\"\n", "receive must be one of auto, direct, threads"),
    ("[can]\nchannels = \"bsc\"\n", "can.channels: expected a list of strings"),
    ("[can.bus_kwargs]\nchannel = \"x\"\n", "channel is a key of [can] itself"),
    ("[drivers]\nsource_rate = \"fast\"\n", "drivers.source_rate: a positive number"),
    ("[drivers]\nstale_periods = 0\n", "stale periods 0: must be at least 1"),
    ("[estimator]\nmax_open = 0\n", "[estimator]: max_open must be a whole number >= 1"),
    ("[estimator.thrusters]\ngyro_sigma = -1\n", "[estimator.thrusters]: gyro_sigma must be a number > 0"),
    ("[estimator.thrusters]\ngyro = 1\n", "[estimator.thrusters]: unknown key gyro"),
    ("service = 3\n", "[service]: expected a table"),
    ("[service\n", "not TOML"),
])
def test_bad_files_name_the_file_the_key_and_what_is_expected(tmp_path, text, says):
    f = tmp_path / "gw.toml"
    f.write_text(text)
    with pytest.raises(ConfigError) as err:
        GatewayConfig.load(f)
    assert says in str(err.value) and str(f) in str(err.value), str(err.value)


def test_the_estimator_and_drivers_sections_are_their_own_settings():
    """No second copy of a default: the [estimator] section is the estimator's CoreSettings."""
    from drivers.health import DEFAULT_TIMING
    from gateway.estimator.core import CoreSettings

    cfg = GatewayConfig()
    assert cfg.estimator is not None and type(cfg.estimator) is CoreSettings
    assert cfg.estimator == CoreSettings() and cfg.drivers.timing() == DEFAULT_TIMING
    assert [f.name for f in dataclasses.fields(cfg)] == ["can", "zenoh", "robot", "service", "drivers", "estimator",
                                                         "recording"]


def test_flags_override_the_file_in_the_printed_configuration(tmp_path):
    f = tmp_path / "gw.toml"
    f.write_text('[can]\ninterface = "virtual"\nchannels = ["bsc"]\nreceive = "threads"\n'
                 '[service]\nhealth_period_s = 0.2\n[can.bus_kwargs]\nserial = 5\n')
    r = bsc("gateway", "--config", str(f), "--health-period", "0.1", "--bus-kwarg", "app_name=x",
            "--source-rate", "lockstep", "--print-config")
    assert r.returncode == 0, r.stderr
    printed = tmp_path / "printed.toml"
    printed.write_text(r.stdout)
    got = GatewayConfig.load(printed)
    assert got.can.interface == "virtual" and got.can.receive == "threads"       # from the file
    assert got.service.health_period_s == 0.1                                     # the flag wins
    assert dict(got.can.bus_kwargs) == {"serial": 5, "app_name": "x"}             # both, merged
    assert got.drivers.source_rate is None
    assert got.estimator == GatewayConfig().estimator                             # the defaults


def test_cli_errors_are_one_line(tmp_path):
    f = tmp_path / "gw.toml"
    f.write_text("[service]\nretry_s = -1\n")
    for args, says in [(("--config", str(f)), "retry_s must be > 0"),
                       (("--config", str(tmp_path / "none.toml")), "no such configuration file"),
                       (("--config", str(ROOT / "deploy" / "zenoh" / "gateway.json5")), "[zenoh] config_file"),
                       ((), "give --interface and --channel, or [can] interface and channels")]:
        r = bsc("gateway", *args)
        assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and says in r.stderr, (args, r.stderr)


def test_a_gateway_run_from_a_file_alone(tmp_path):
    """Everything from the file: buses, robot, zenoh endpoint, health period, duration, recording;
    the recorded session says which configuration made it."""
    from mcap.reader import make_reader

    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    f = tmp_path / "gw.toml"
    f.write_text(f'[can]\ninterface = "virtual"\nchannels = ["bsc-config-test"]\n'
                 f'[zenoh]\nlisten = ["{ep}"]\n[robot]\ndescription = "paper_robot"\n'
                 f'[service]\nhealth_period_s = 0.1\nduration_s = 60.0\n[recording]\npath = "run.mcap"\n')
    proc = subprocess.Popen([sys.executable, "-m", "gateway.cli", "gateway", "--config", str(f)], cwd=ROOT,
                            env=dict(os.environ, OPENBLAS_NUM_THREADS="1"), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        import threading

        got = threading.Event()
        with zenoh.open(make_config(connect=[ep])) as s:
            sub = s.declare_subscriber(keys.health("paper_robot"), lambda smp: got.set())
            ok = got.wait(60.0)
            sub.undeclare()
        assert ok, proc.stderr.read() if proc.poll() is not None else "no health received"
    finally:
        proc.terminate()
        out, err = proc.communicate(timeout=60)
    assert "bsc gateway: robot paper_robot, buses arm0=bsc-config-test-arm0" in out, err
    with open(tmp_path / "run.mcap", "rb") as fh:
        meta = {m.name: m.metadata for m in make_reader(fh).iter_metadata()}
    recorded = tmp_path / "recorded.toml"
    recorded.write_text(meta["bsc.session"]["gateway_config"])
    cfg = GatewayConfig.load(recorded)
    assert cfg.service.health_period_s == 0.1 and cfg.can.channels == ("bsc-config-test",)
