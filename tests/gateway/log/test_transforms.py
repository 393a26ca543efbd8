"""The robot's frame tree in a recorded session (``/tf``, ``foxglove.FrameTransforms``) and its
URDF (``/robot_description``), as Foxglove's 3D panel reads them, checked against the
simulator's ground truth: the end effectors' poses composed from the recorded transforms are
where the simulated robot's end effectors were."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

import robot_description
from gateway.log import reader
from gateway.log.foxglove import (FRAME_TRANSFORMS_SCHEMA_NAME, ROBOT_DESCRIPTION_TOPIC, TF_PERIOD_NS, TF_TOPIC,
                                  WORLD_FRAME, FrameTransforms)

# The recorded transforms come from the sensors, the truth from the simulator's state: they
# differ by the IMU's attitude noise (0.002 deg, 1 sigma), the 20-bit encoders' steps (6e-6 rad)
# and the age of the IMU sample at a tick (up to 2 ms at 500 Hz; the spacecraft turns at up to
# 0.17 rad/s here). Each tick is compared with the truth of the steps its samples can be from
# (the last SAMPLE_AGE_STEPS + 1 ms); measured 2026-11-26: at worst 1.4 mm and 0.45 mrad over arms
# up to 5.2 m long. A wrong joint axis, origin or IMU mounting errs by tens of centimetres.
POSITION_TOL_M = 3e-3
ANGLE_TOL_RAD = 1e-3
SAMPLE_AGE_STEPS = 2


def _simulated_session(path: Path, scenario: str, duration_s: float, *, samples: bool):
    """The firmware's frames of a simulated session through the gateway's session engine into a
    recording, as ``bsc sim --series`` records (``samples=False``: as a replay does)."""
    from gateway.engine import Session
    from gateway.engine.sinks import RecorderSink
    from gateway.log.recorder import Recorder
    from robot_description.thrusters import ThrusterLayout
    from simulator import scenario as scenarios
    from simulator.engine import Simulation
    from simulator.firmware import Firmware

    sc = scenarios.load(scenario).replace(duration_s=duration_s)
    sim = Simulation(sc)
    with Recorder(path, overwrite=True) as rec:
        rec.add_session_context(urdf_text=sim.robot.urdf)
        with Session(sim.robot, [RecorderSink(rec, offline=True)], samples=samples,
                     layout=ThrusterLayout.from_config(sc.cfg.thrusters)) as ses:
            fw = Firmware(sim.robot)
            while sim.k < sim.n_steps:
                for bus, msg in fw.frames(sim.step()):
                    ses.feed(bus, msg)
    return sim


def _se3(t: dict) -> pin.SE3:
    r, p = t["rotation"], t["translation"]
    q = pin.Quaternion(r["w"], r["x"], r["y"], r["z"])
    return pin.SE3(q.matrix(), np.array([p["x"], p["y"], p["z"]]))


def _compose(transforms: list[dict], child: str) -> pin.SE3:
    """``child``'s pose in ``world`` from one message's parent -> child transforms."""
    parent_of = {t["child_frame_id"]: t for t in transforms}
    M = pin.SE3.Identity()
    while child != WORLD_FRAME:
        t = parent_of[child]                   # KeyError: a frame not connected to world
        M = _se3(t) * M
        child = t["parent_frame_id"]
    return M


@pytest.fixture(scope="module")
def three_arm_session(tmp_path_factory):
    path = tmp_path_factory.mktemp("tf") / "three_arm.mcap"
    sim = _simulated_session(path, "three_arm", 1.0, samples=False)
    return path, sim


def test_end_effector_poses_from_tf_match_the_simulated_truth(three_arm_session):
    """Spatial arms (axes z, y, y), an IMU mounted turned by 90 degrees: every arm's
    world -> end-effector pose composed from each /tf message equals the simulator's true pose
    (Pinocchio's forward kinematics of its true state; position relative to the spacecraft's
    centre of mass, the world frame's origin) within the stated tolerance."""
    path, sim = three_arm_session
    robot, tr = sim.robot, sim.trace.arrays
    model, data = robot.model, robot.data()
    msgs = list(reader.read_messages(path, [TF_TOPIC]))
    assert 45 <= len(msgs) <= 50                        # 1 s at 50 Hz
    t_s, q_true = tr["t_s"][: sim.k], tr["q"][: sim.k]
    worst_p = worst_r = 0.0
    for m in msgs:
        assert m.schema_name == FRAME_TRANSFORMS_SCHEMA_NAME
        tfs = m.data["transforms"]
        stamp = tfs[0]["timestamp"]
        assert all(t["timestamp"] == stamp for t in tfs)
        assert stamp["sec"] * 1_000_000_000 + stamp["nsec"] == m.log_time_ns
        # the samples a tick holds are up to one IMU period (2 ms) old: the truth of those steps
        k0 = int(np.argmin(np.abs(t_s - m.log_time_ns / 1e9)))
        best = (math.inf, math.inf)
        for k in range(max(0, k0 - SAMPLE_AGE_STEPS), k0 + 1):
            q = q_true[k]
            pin.framesForwardKinematics(model, data, q)
            err_p = err_r = 0.0
            for arm in robot.arms:
                truth = data.oMf[arm.ee_frame]
                got = _compose(tfs, f"{arm.name}_ee")
                err_p = max(err_p, np.linalg.norm(got.translation - (truth.translation - q[:3])))
                err_r = max(err_r, np.linalg.norm(pin.log3(got.rotation.T @ truth.rotation)))
            best = min(best, (err_p, err_r))
        worst_p, worst_r = max(worst_p, best[0]), max(worst_r, best[1])
    assert worst_p < POSITION_TOL_M and worst_r < ANGLE_TOL_RAD, (worst_p, worst_r)
    # the arms moved and the spacecraft turned: a test of the angles, not of a robot at rest
    assert np.ptp(q_true[:, 7:], axis=0).max() > 0.05


def test_frame_ids_are_the_urdf_links_and_the_urdf_is_in_the_log(three_arm_session):
    path, sim = three_arm_session
    links = {j.child for j in robot_description.urdf_joints(sim.robot.urdf)} | {"spacecraft"}
    msgs = list(reader.read_messages(path, [TF_TOPIC, ROBOT_DESCRIPTION_TOPIC]))
    assert msgs[0].topic == ROBOT_DESCRIPTION_TOPIC and msgs[1].topic == TF_TOPIC
    assert msgs[0].log_time_ns == msgs[1].log_time_ns                 # there when the first transforms are
    assert msgs[0].data == {"data": sim.robot.urdf, "robot": "three_arm"}
    assert "<visual>" in msgs[0].data["data"]
    tf = [m for m in msgs if m.topic == TF_TOPIC]
    for m in tf:
        children = [t["child_frame_id"] for t in m.data["transforms"]]
        assert sorted(children) == sorted(links)              # every link, once, from the first message on
        assert {t["parent_frame_id"] for t in m.data["transforms"]} <= links | {WORLD_FRAME}
    times = [m.log_time_ns for m in tf]
    assert all(b - a >= TF_PERIOD_NS - 2_000_000 for a, b in zip(times, times[1:]))   # 50 Hz at most


def test_transforms_from_samples_are_the_urdf_kinematics():
    """One joint state through :class:`FrameTransforms` (objects, as ``bsc record`` feeds it),
    composed: Pinocchio's forward kinematics of the same q, to rounding."""
    from drivers.samples import ImuSample, JointSample

    robot = robot_description.load("three_arm")
    rng = np.random.default_rng(3)
    q = pin.neutral(robot.model)
    q[7:] = rng.uniform(-2.5, 2.5, robot.n_joints)
    quat = pin.Quaternion(pin.rpy.rpyToMatrix(0.3, -0.7, 2.0))
    q[3:7] = quat.coeffs()                               # x y z w: the spacecraft's attitude
    data = robot.data()
    pin.framesForwardKinematics(robot.model, data, q)
    R_imu_world = pin.Quaternion(data.oMf[robot.imu_frame].rotation)
    tf = FrameTransforms(robot)
    out = [tf.sample(ImuSample(0, 0, (R_imu_world.w, R_imu_world.x, R_imu_world.y, R_imu_world.z),
                               (0, 0, 0), (0, 0, 0)))]
    for i, name in enumerate(robot.joint_names):
        out.append(tf.sample(JointSample(name, 1000 + i, 0, float(q[7 + i]), 0.0)))
    assert out == [None] * len(out)                      # the first period is not over yet
    msg = tf.sample(JointSample(robot.joint_names[0], TF_PERIOD_NS, 1, float(q[7]), 0.0))
    assert msg is not None
    for frame in [a.ee_frame for a in robot.arms] + [robot.imu_frame]:
        name = robot.model.frames[frame].name
        got = _compose(msg["transforms"], name)
        assert np.allclose(got.homogeneous, data.oMf[frame].homogeneous, atol=1e-12), name


def test_bad_samples_are_ignored_and_never_written():
    """A quaternion of no length or not finite, an angle that is NaN, a joint the robot does not
    have: ignored (counted), the previous values hold, nothing crashes, no NaN reaches JSON."""
    import json

    from drivers.samples import ImuSample, JointSample

    robot = robot_description.load("paper_robot")
    tf = FrameTransforms(robot)
    good = (math.cos(0.2), 0.0, 0.0, math.sin(0.2))
    tf.sample(ImuSample(0, 0, good, (0, 0, 0), (0, 0, 0)))
    for bad in [(0, 0, 0, 0), (math.nan, 0, 0, 1), (1, 0, math.inf, 0), ("a", 0, 0, 0), (1, 2), (1e200, 0, 0, 0)]:
        tf.sample(ImuSample(1, 0, bad, (0, 0, 0), (0, 0, 0)))
    tf.sample(JointSample("arm0/j1", 2, 0, 0.5, 0.0))
    tf.sample(JointSample("arm0/j1", 3, 0, math.nan, 0.0))
    tf.sample(JointSample("arm9/j1", 4, 0, 1.0, 0.0))
    assert tf.ignored == 7
    msg = tf.sample(JointSample("arm0/j2", TF_PERIOD_NS * 2, 0, 0.25, 0.0))
    text = json.dumps(msg, allow_nan=False)
    by_child = {t["child_frame_id"]: t for t in json.loads(text)["transforms"]}
    assert by_child["spacecraft"]["rotation"] == pytest.approx({"x": 0, "y": 0, "z": math.sin(0.2), "w": math.cos(0.2)})
    assert by_child["arm0_link1"]["rotation"] == pytest.approx({"x": 0, "y": 0, "z": math.sin(0.25),
                                                                "w": math.cos(0.25)})
    assert "arm1_link1" not in by_child and "arm1_ee" in by_child     # no angle yet: left out


def test_a_replay_and_a_series_session_carry_the_transforms(tmp_path, bsc):
    """``bsc sim --series`` records /tf; ``bsc replay --out`` (no --samples) writes it again from
    the log's frames, the same transforms (the same samples through the same code)."""
    out = tmp_path / "series"
    r = bsc("sim", "--series", "healthy", "--sessions", "1", "--duration", "0.5", "--out", out, "--quiet",
            timeout=300)
    assert r.returncode == 0, r.stderr
    session = out / "session_0000.mcap"
    r = bsc("replay", session, "--out", tmp_path / "replay", "--quiet", timeout=300)
    assert r.returncode == 0, r.stderr
    rec = [(m.log_time_ns, m.data) for m in reader.read_messages(session, [TF_TOPIC])]
    rep = [(m.log_time_ns, m.data) for m in reader.read_messages(tmp_path / "replay" / "replay.mcap", [TF_TOPIC])]
    assert len(rec) >= 20 and rep == rec


def test_bsc_record_makes_the_transforms_from_the_zenoh_samples(tmp_path):
    """``bsc record``'s path: samples arriving as zenoh payloads (objects, one at a time)."""
    from drivers.samples import ImuSample, JointSample
    from gateway import codec
    from gateway.commands.record import Recording
    from gateway.log.recorder import Recorder

    robot = robot_description.load("paper_robot")
    path = tmp_path / "rec.mcap"
    t0 = 1_790_000_000_000_000_000
    with Recorder(path) as rec:
        recording = Recording(rec, {}, None, None, robot=robot)
        for i in range(100):                                     # 100 ms at 1 kHz
            t = t0 + i * 1_000_000
            if i % 2 == 0:
                recording.on_payload("bsc/paper_robot/samples/imu",
                                     codec.encode(ImuSample(t, i % 256, (1.0, 0.0, 0.0, 0.0), (0, 0, 0), (0, 0, 0))))
            for name in robot.joint_names:
                recording.on_payload(f"bsc/paper_robot/samples/joint/{name}",
                                     codec.encode(JointSample(name, t, i % 256, 0.001 * i, 0.0)))
        assert recording.refused == 0 and not recording.rejected
    tf = list(reader.read_messages(path, [TF_TOPIC]))
    assert [m.log_time_ns - t0 for m in tf] == [20_000_000, 40_000_000, 60_000_000, 80_000_000]
    last = {t["child_frame_id"]: t for t in tf[-1].data["transforms"]}
    # the 80 ms tick came with that ms's IMU sample, before its joint samples: the angles of 79 ms
    assert last["arm0_link1"]["rotation"]["z"] == pytest.approx(math.sin(0.079 / 2))
    assert len(list(reader.read_messages(path, [ROBOT_DESCRIPTION_TOPIC]))) == 1


def test_a_batch_of_rows_gives_what_the_rows_one_by_one_give():
    """The numpy path (a replay's chunks) and the loop (live, a frame at a time) are one
    behaviour: the same messages at the same times, bad values (NaN angles, zero quaternions,
    unknown joints) ignored alike."""
    from drivers.kernel import EVENT_DTYPE, IMU, JOINT, WRENCH

    robot = robot_description.load("paper_robot")
    names = ("arm0/j1", "arm0/j2", "arm1/j1", "arm1/j2", "arm9/j1")      # the drivers' order, one unknown
    rng = np.random.default_rng(7)
    n = 3000
    ev = np.zeros(n, EVENT_DTYPE)
    ev["kind"] = rng.choice([JOINT, JOINT, IMU, WRENCH], n)
    ev["device"] = np.where(ev["kind"] == JOINT, rng.integers(0, len(names), n), 0)
    ev["values"][:, :4] = rng.normal(size=(n, 4))
    ev["values"][rng.random(n) < 0.05, 0] = np.nan
    ev["values"][rng.random(n) < 0.05, :4] = 0.0
    log = 1_000_000_000 + np.cumsum(rng.integers(0, 400_000, n)).astype(np.int64)
    batch, single = FrameTransforms(robot), FrameTransforms(robot)
    got = [m for a in range(0, n, 500) for m in batch.rows(ev[a:a + 500], log[a:a + 500], names)]
    want = [m for i in range(n) for m in single.rows(ev[i:i + 1], log[i:i + 1], names)]
    assert len(want) > 20 and got == want
    assert batch.ignored == single.ignored > 0


def test_each_rotated_file_gets_the_urdf(tmp_path):
    """A split recording: every file with transforms has the URDF too, at or before its first
    transforms (Foxglove opens one file at a time)."""
    from drivers.samples import ImuSample
    from gateway.log.foxglove import TransformWriter
    from gateway.log.recorder import Recorder

    robot = robot_description.load("paper_robot")
    with Recorder(tmp_path / "split.mcap", chunk_size=1024, rotate_bytes=4096) as rec:
        tw = TransformWriter(rec, robot)
        for i in range(60):
            assert tw.sample(ImuSample(i * TF_PERIOD_NS, i % 256, (1.0, 0.0, 0.0, 0.0), (0, 0, 0), (0, 0, 0)))
            rec.flush()                   # the writer has rotated before the next look at the files
        paths = rec.paths
    assert len(paths) >= 5
    for p in paths:
        msgs = list(reader.read_messages(p, [TF_TOPIC, ROBOT_DESCRIPTION_TOPIC]))
        if any(m.topic == TF_TOPIC for m in msgs):
            assert msgs[0].topic == ROBOT_DESCRIPTION_TOPIC, p.name


def test_bsc_record_over_zenoh_writes_the_transforms(tmp_path):
    """The samples a gateway publishes, received by bsc record's subscriber on its zenoh thread:
    /tf from them, nothing refused."""
    import time

    import zenoh

    from drivers.samples import ImuSample, JointSample
    from gateway import codec, keys
    from gateway.commands.record import Recording
    from gateway.log.recorder import Recorder
    from gateway.zenoh_config import make_config
    from support import free_port

    robot = robot_description.load("paper_robot")
    ep = f"tcp/127.0.0.1:{free_port()}"
    path = tmp_path / "z.mcap"
    n_ms = 200
    with zenoh.open(make_config(listen=[ep])) as rec_s, zenoh.open(make_config(connect=[ep])) as pub_s, \
            Recorder(path) as rec:
        with Recording(rec, {}, rec_s, keys.everything(robot.name), robot=robot) as recording:
            block = zenoh.CongestionControl.BLOCK       # every sample must arrive (not the sensors' DROP)
            pubs = {name: pub_s.declare_publisher(keys.joint(robot.name, name), congestion_control=block)
                    for name in robot.joint_names}
            imu = pub_s.declare_publisher(keys.imu(robot.name), congestion_control=block)
            deadline = time.monotonic() + 30
            while not all(p.matching_status.matching for p in [imu, *pubs.values()]):
                assert time.monotonic() < deadline, "no subscriber matched"
                time.sleep(0.005)
            for i in range(n_ms):
                t = 1_000_000_000 + i * 1_000_000
                for name, p in pubs.items():
                    p.put(codec.encode(JointSample(name, t, i % 256, 0.01 * i, 0.0)))
                imu.put(codec.encode(ImuSample(t, i % 256, (1.0, 0.0, 0.0, 0.0), (0, 0, 0), (0, 0, 0))))
            want = n_ms * (len(pubs) + 1)
            while sum(recording.samples.values()) + recording.refused + sum(recording.rejected.values()) < want:
                assert time.monotonic() < deadline, recording.summary()
                time.sleep(0.005)
            assert recording.refused == 0 and not recording.rejected
    tf = list(reader.read_messages(path, [TF_TOPIC]))
    assert len(tf) == n_ms // 20 - 1                      # a tick per 20 ms after the first
    assert len(list(reader.read_messages(path, [ROBOT_DESCRIPTION_TOPIC]))) == 1
