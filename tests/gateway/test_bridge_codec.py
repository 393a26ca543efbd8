"""gateway.codec round-trips every sample and health dataclass and refuses anything else."""
from __future__ import annotations

import pytest
from hypothesis import given, settings, strategies as st

from drivers.samples import (BusHealth, DeviceHealth, ImuSample, JointSample, ThrusterCommand, TorqueCommand,
                             WrenchSample)
from gateway import codec, keys
from gateway.efforts import Alert, JointEfforts, ThrusterEffort

fl = st.floats(allow_nan=False, allow_infinity=False)
v3 = st.tuples(fl, fl, fl)
i64 = st.integers(-(2**63), 2**63 - 1)
name = st.text(min_size=1, max_size=12)
reasons = st.lists(st.tuples(name, st.integers(0, 10**9)), max_size=4).map(tuple)

SAMPLES = st.one_of(
    st.builds(WrenchSample, name, i64, st.integers(0, 255), v3, v3, st.booleans(), st.integers(0, 255)),
    st.builds(ImuSample, i64, st.integers(0, 255), st.tuples(fl, fl, fl, fl), v3, v3, st.booleans(),
              st.integers(0, 2**32 - 1)),
    st.builds(JointSample, name, i64, st.integers(0, 255), fl, fl, st.booleans(), st.integers(0, 255)),
    st.builds(TorqueCommand, name, i64, st.integers(0, 255), fl, st.booleans()),
    st.builds(ThrusterCommand, i64, st.integers(0, 255), v3, v3, st.integers(0, 2**32 - 1), st.booleans()),
    st.builds(DeviceHealth, name, name, i64, st.integers(0), st.integers(0), st.integers(0), reasons, i64,
              st.booleans(), st.integers(0), st.integers(0)),
    st.builds(BusHealth, name, i64, st.integers(0), reasons, fl, reasons),
    st.builds(JointEfforts, name, i64, st.lists(name, max_size=3).map(tuple), st.lists(fl, max_size=3).map(tuple),
              st.lists(fl, max_size=3).map(tuple), st.lists(fl, max_size=3).map(tuple), i64,
              st.lists(fl, max_size=3).map(tuple), st.booleans(), st.lists(name, max_size=3).map(tuple)),
    st.builds(ThrusterEffort, i64, v3, v3, v3, v3, i64, st.integers(0, 2**32 - 1), st.booleans(),
              st.lists(name, max_size=3).map(tuple)),
    st.builds(Alert, name, name, name, name, name, name, i64, i64, st.text(max_size=40),
              st.lists(st.tuples(name, fl), max_size=3).map(tuple)),
)


@settings(max_examples=300, deadline=None)
@given(SAMPLES)
def test_round_trip(sample):
    assert codec.decode(codec.encode(sample)) == sample


@pytest.mark.parametrize("payload", [
    b"", b"\xff\xfe", b"[]", b'{"type": "os.system", "v": 1}', b'{"type": "WrenchSample", "v": 2}',
    b'{"type": "JointSample", "v": 1, "device": "a", "t_ns": 1, "counter": 1, "angle_rad": "x", "rate_rad_s": 0}',
    b'{"type": "JointSample", "v": 1, "device": "a", "t_ns": 1, "counter": 1, "angle_rad": 0}',
    b'{"type": "JointSample", "v": 1, "device": "a", "t_ns": 1.5, "counter": 1, "angle_rad": 0, "rate_rad_s": 0}',
    b'{"type": "TorqueCommand", "v": 1, "device": "a", "t_ns": 1, "counter": 1, "torque_nm": 0, "evil": 1}',
    b'{"type": "WrenchSample", "v": 1, "device": "a", "t_ns": 1, "counter": 1, "force_n": [1, 2], '
    b'"torque_nm": [0,0,0]}',
])
def test_bad_payloads_refused(payload):
    with pytest.raises(codec.CodecError):
        codec.decode(payload)


def test_non_finite_refused_on_encode():
    with pytest.raises(codec.CodecError):
        codec.encode(TorqueCommand("a/j", 0, 0, float("inf")))


def test_keys():
    assert keys.wrench("paper_robot", "arm0") == "bsc/paper_robot/sensors/wrench/arm0"
    assert keys.for_sample("r", JointSample("arm0/j1", 0, 0, 0.0, 0.0)) == "bsc/r/sensors/joint/arm0/j1"
    assert keys.device_health("r", "arm0/torque_cmd") == "bsc/r/health/device/arm0/torque_cmd"
    assert keys.for_sample("r", ThrusterEffort(0, (0.0,) * 3, (0.0,) * 3, (0.0,) * 3, (0.0,) * 3, 0, 0, True)) \
        == "bsc/r/efforts/thrusters"
    assert keys.joint_efforts("r", "arm1") == "bsc/r/efforts/joints/arm1"
    assert keys.alerts("r") == "bsc/r/alerts"
    with pytest.raises(ValueError):
        keys.wrench("r", "a*")


def test_publishers_block_for_efforts_alerts_health_and_drop_for_samples():
    import zenoh

    from gateway import codec

    class Session:
        def declare_publisher(self, key, **kw):
            return kw["congestion_control"]

    s = Session()
    for key in ("bsc/r/efforts/thrusters", "bsc/r/alerts", "bsc/r/health/bus/arm0"):
        assert codec.declare_publisher(s, key) == zenoh.CongestionControl.BLOCK, key
    for key in ("bsc/r/sensors/imu", "bsc/r/sensors/commands/valves"):
        assert codec.declare_publisher(s, key) == zenoh.CongestionControl.DROP, key
