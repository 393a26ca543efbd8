"""The compiled thruster filter (gateway/estimator/thruster_kernel.py): agreement with the numpy
ThrusterFilter on a simulated stream (rigid-body truth, PWPFM-like valve pulses, arm reactions,
noisy IMU), the same bits whatever the batching, and the structure it relies on (bitwise
symmetric P, zero cross-covariance of a valve that never fired)."""
from __future__ import annotations

import numpy as np
import pytest

import robot_description as rd
from gateway.estimator import EstimatorModel
from gateway.estimator.thruster_kernel import IMU, STEP, WRENCH_ONLY, CompiledThrusterFilter
from gateway.estimator.thrusters import ThrusterFilter, ThrusterFilterSettings
from robot_description.thrusters import ThrusterLayout

REL = 1e-9            # agreement with the numpy form


@pytest.fixture(scope="module")
def paper():
    return EstimatorModel.from_robot(rd.load("paper_robot")), ThrusterLayout.named()


def _stream(model: EstimatorModel, layout: ThrusterLayout, *, steps: int, imu_steps: int, seed: int,
            dt: float = 1e-3, never: tuple[int, ...] = (), common: float = 1.0) -> dict[str, np.ndarray]:
    """Events as the live estimator produces them: per 1 kHz step a STEP (a WRENCH_ONLY for ~1 %
    untrusted steps), and after every ``imu_steps``-th step an IMU sample (~2 % lost). Truth: each
    valve's wrench off nominal by a few %, valves pulsing (~1.7 open), arm reactions (sines +
    noise), Euler-integrated rigid-body rates; IMU = interval means + the settings' noise. Valves
    in ``never`` never open; ``common`` multiplies every thrust (a shared gain: the tank pressure)."""
    rng = np.random.default_rng(seed)
    n = layout.n
    Is, Is_inv, m, r, R = model.inertia_s, np.linalg.inv(model.inertia_s), model.mass_s, model.r_imu, model.R_imu
    f = layout.dir * (layout.max_n * (1 + 0.05 * rng.normal(size=n)))[:, None] + rng.normal(0, 1.0, (n, 3))
    f = common * f
    W = np.hstack([f, np.cross(layout.pos_m, f) + rng.normal(0, 0.5, (n, 3))])
    amp, freq, phase = rng.uniform(10, 60, 6), rng.uniform(0.1, 0.5, 6), rng.uniform(0, 2 * np.pi, 6)
    w = np.array([0.01, -0.02, 0.015])
    on = np.zeros(n, dtype=bool)
    allowed = np.ones(n, dtype=bool)
    allowed[list(never)] = False
    t0 = 1_700_000_000 * 10 ** 9                 # wall-clock sized: float(t_ns) rounds (ulp 256 ns)
    step_ns = round(dt * 1e9)
    ev: dict[str, list] = {k: [] for k in ("kind", "t_ns", "arm", "mask", "accel", "rate")}
    acc_sum, w_sum = np.zeros(3), np.zeros(3)

    def add(kind, t, arm=np.zeros(6), mask=0, accel=np.zeros(3), rate=np.zeros(3)):
        for k, v in zip(ev, (kind, t, arm, mask, accel, rate)):
            ev[k].append(v)

    for s in range(1, steps + 1):
        t = t0 + s * step_ns
        on = np.where(on, rng.random(n) > 0.2, rng.random(n) < 0.02) & allowed
        arm = amp * np.sin(2 * np.pi * freq * s * dt + phase) + rng.normal(0, 0.5, 6)
        thr = on.astype(float) @ W
        dw = Is_inv @ (thr[3:] + arm[3:] - np.cross(w, Is @ w))
        w = w + dw * dt
        acc_sum += (thr[:3] + arm[:3]) / m + np.cross(dw, r) + np.cross(w, np.cross(w, r))
        w_sum += w
        mask = sum(1 << int(i) for i in np.flatnonzero(on))
        add(STEP if rng.random() > 0.01 else WRENCH_ONLY, t, arm, mask)
        if s % imu_steps == 0:
            accel = R.T @ (acc_sum / imu_steps) + rng.normal(0, 3.1e-3, 3)
            rate = R.T @ (w_sum / imu_steps) + rng.normal(0, 2.9e-5, 3)
            acc_sum, w_sum = np.zeros(3), np.zeros(3)
            if rng.random() > 0.02:
                add(IMU, t, accel=accel, rate=rate)
    return {"kind": np.array(ev["kind"], dtype=np.int64), "t_ns": np.array(ev["t_ns"], dtype=np.int64),
            "arm": np.array(ev["arm"]), "mask": np.array(ev["mask"], dtype=np.int64),
            "accel": np.array(ev["accel"]), "rate": np.array(ev["rate"])}


def _reference(kf: ThrusterFilter, ev) -> tuple[np.ndarray, np.ndarray]:
    """The events through the numpy filter, as live.py drives it: wrench of each step, applied flags."""
    shifts = np.arange(kf.n)
    N = len(ev["kind"])
    wr, applied = np.zeros((N, 6)), np.zeros(N, dtype=bool)
    for k in range(N):
        t = int(ev["t_ns"][k])
        if ev["kind"][k] == IMU:
            applied[k] = kf.imu(t, ev["accel"][k], ev["rate"][k])
        else:
            v = ((int(ev["mask"][k]) >> shifts) & 1).astype(float)
            wr[k] = kf.wrench(v)
            if ev["kind"][k] == STEP:
                kf.push_epoch(t, ev["arm"][k], v)
    return wr, applied


def _single(kf: CompiledThrusterFilter, ev, lo: int = 0, hi: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The events one call each (the live caller's way)."""
    hi = len(ev["kind"]) if hi is None else hi
    wr, applied = np.zeros((hi - lo, 6)), np.zeros(hi - lo, dtype=bool)
    for k in range(lo, hi):
        t, kind, mask = int(ev["t_ns"][k]), ev["kind"][k], int(ev["mask"][k])
        if kind == IMU:
            applied[k - lo] = kf.imu(t, ev["accel"][k], ev["rate"][k])
        else:
            wr[k - lo] = kf.wrench(mask)
            if kind == STEP:
                kf.push_epoch(t, ev["arm"][k], mask)
    return wr, applied


def _run(kf: CompiledThrusterFilter, ev, lo: int = 0, hi: int | None = None):
    return kf.run(*(ev[k][lo:hi] for k in ("kind", "t_ns", "arm", "mask", "accel", "rate")))


def _assert_agree(kf: CompiledThrusterFilter, ref: ThrusterFilter) -> None:
    sigma = np.sqrt(np.diag(ref.P))
    dx = np.abs(kf.x - ref.x)
    assert dx.max() <= REL * np.abs(ref.x).max()
    assert np.all(dx <= REL * np.maximum(np.abs(ref.x), sigma))
    dP = np.abs(kf.P - ref.P)
    assert dP.max() <= REL * np.abs(ref.P).max()
    assert np.all(dP <= REL * np.outer(sigma, sigma))          # relative to the correlation scale
    assert np.allclose(kf.w, ref.w, rtol=1e-13, atol=0)
    assert np.array_equal(kf.P, kf.P.T)                        # symmetric to the bit, never symmetrised


def test_agrees_with_the_numpy_filter_after_4000_updates(paper):
    model, layout = paper
    ev = _stream(model, layout, steps=8500, imu_steps=2, seed=1)
    ref = ThrusterFilter(model, layout, dt=1e-3, imu_steps=2)
    kf = CompiledThrusterFilter(model, layout, dt=1e-3, imu_steps=2)
    r_wr, r_app = _reference(ref, ev)
    wr, app = _run(kf, ev)
    assert np.array_equal(app, r_app)                          # the same gating of steps and gyro rows
    assert kf.updates == ref.updates >= 4000
    _assert_agree(kf, ref)
    assert np.abs(wr - r_wr).max() <= REL * np.abs(r_wr).max()
    assert np.allclose(kf.efficiency(), ref.efficiency(), rtol=REL, atol=0)
    assert np.allclose(kf.bias, ref.bias, rtol=0, atol=REL * np.abs(ref.x).max())
    assert np.shares_memory(kf.W, kf.x) and kf.W.shape == (layout.n, 6)


@pytest.mark.parametrize("robot, imu_steps", [("paper_robot", 1), ("three_arm", 3)])
def test_agrees_with_other_imu_rates_and_robots(robot, imu_steps):
    model, layout = EstimatorModel.from_robot(rd.load(robot)), ThrusterLayout.named()
    ev = _stream(model, layout, steps=500 * imu_steps, imu_steps=imu_steps, seed=2)
    ref = ThrusterFilter(model, layout, dt=1e-3, imu_steps=imu_steps)
    kf = CompiledThrusterFilter(model, layout, dt=1e-3, imu_steps=imu_steps)
    _, r_app = _reference(ref, ev)
    _, app = _single(kf, ev)
    assert np.array_equal(app, r_app) and kf.updates == ref.updates > 400
    _assert_agree(kf, ref)


def test_one_batch_chunks_and_single_calls_give_the_same_bits(paper):
    model, layout = paper
    ev = _stream(model, layout, steps=3300, imu_steps=2, seed=3)
    N = len(ev["kind"])
    assert N > 4000 and {STEP, IMU, WRENCH_ONLY} <= set(ev["kind"].tolist())
    whole, chunked, single = (CompiledThrusterFilter(model, layout) for _ in range(3))
    w1, a1 = _run(whole, ev)
    parts = [_run(chunked, ev, lo, lo + 1000) for lo in range(0, N, 1000)]
    w2, a2 = np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
    w3, a3 = _single(single, ev)
    for other, (wo, ao) in ((chunked, (w2, a2)), (single, (w3, a3))):
        assert np.array_equal(whole.x.view(np.uint64), other.x.view(np.uint64))
        assert np.array_equal(whole.P.view(np.uint64), other.P.view(np.uint64))
        assert np.array_equal(w1.view(np.uint64), wo.view(np.uint64)) and np.array_equal(a1, ao)
        assert np.array_equal(whole.w, other.w) and whole.updates == other.updates
        for a, b in zip(whole._state, other._state):        # history, counters, everything
            assert np.array_equal(a, b)
    assert whole.updates > 1500


def test_a_valve_that_never_fired_keeps_its_prior_and_zero_cross_covariance(paper):
    """Without a shared gain in the prior, the kernels skip a valve that never fired."""
    model, layout = paper
    own = ThrusterFilterSettings(common_gain_sigma=0.0)
    ev = _stream(model, layout, steps=1200, imu_steps=2, seed=4, never=(5, 11))
    ref = ThrusterFilter(model, layout, settings=own)
    kf = CompiledThrusterFilter(model, layout, settings=own)
    prior = CompiledThrusterFilter(model, layout, settings=own)
    _reference(ref, ev)
    _run(kf, ev)
    _assert_agree(kf, ref)
    for i in (5, 11):
        b = slice(6 * i, 6 * i + 6)
        rest = np.ones(kf.ns, dtype=bool)
        rest[b] = False
        assert not kf.P[b][:, rest].any() and not ref.P[b][:, rest].any()
        assert np.array_equal(kf.x[b], prior.x[b])
        assert np.array_equal(kf.P[b, b], ref.P[b, b])          # the prior plus the same random walk
        assert np.all(np.diag(kf.P[b, b]) > np.diag(prior.P[b, b]))


def test_the_shared_gain_teaches_the_valves_that_never_fired(paper):
    """Every thrust 8 % low (the tank pressure), valves 5 and 11 never open: with the shared gain
    in the prior (the default) the filter moves their thrust to about 0.92 of nominal from what the
    others deliver; with each gain its own they stay at the prior's nominal thrust."""
    model, layout = paper
    ev = _stream(model, layout, steps=3000, imu_steps=2, seed=6, never=(5, 11), common=0.92)
    shared = CompiledThrusterFilter(model, layout)
    ref = ThrusterFilter(model, layout)
    own = CompiledThrusterFilter(model, layout, settings=ThrusterFilterSettings(common_gain_sigma=0.0))
    _run(shared, ev)
    _reference(ref, ev)
    _run(own, ev)
    _assert_agree(shared, ref)
    def along(kf: CompiledThrusterFilter, i: int) -> float:        # thrust along the nominal direction
        return float(kf.W[i, :3] @ layout.dir[i]) / layout.max_n[i]

    for i in (5, 11):
        assert abs(along(shared, i) - 0.92) < 0.03, (i, along(shared, i))
        assert along(own, i) == 1.0
    fired = [i for i in range(layout.n) if i not in (5, 11)]
    assert np.mean([along(shared, i) for i in fired]) < 0.95


def test_wrench_is_the_sum_of_the_open_valves_in_ascending_order(paper):
    model, layout = paper
    kf = CompiledThrusterFilter(model, layout)
    kf.x[:] = np.random.default_rng(5).normal(0, 100, kf.ns)
    for mask in (0, 1, 0b101, (1 << layout.n) - 1, 0b1000100010001000):
        want = np.zeros(6)
        for i in range(layout.n):
            if mask >> i & 1:
                want = want + kf.W[i]
        assert np.array_equal(kf.wrench(mask), want)
        v = ((mask >> np.arange(layout.n)) & 1).astype(float)
        assert np.allclose(kf.wrench(mask), v @ kf.W, rtol=1e-14, atol=1e-12)


def test_gaps_and_bad_input(paper):
    model, layout = paper
    kf = CompiledThrusterFilter(model, layout)
    t = 5_000_000_000
    assert not kf.imu(t, np.zeros(3), [0.0, 0.0, 0.1])          # no steps yet: kept rate, no update
    assert kf.updates == 0 and np.array_equal(kf.w, model.R_imu @ np.array([0.0, 0.0, 0.1]))
    kf.push_epoch(t + 1_000_000, np.zeros(6), 1)
    kf.push_epoch(t + 3_000_000, np.zeros(6), 1)                # the step at t + 2 ms is missing
    assert not kf.imu(t + 3_000_000, np.zeros(3), np.zeros(3))
    kf.push_epoch(t + 4_000_000, np.zeros(6), 1)
    assert kf.imu(t + 4_000_000, np.zeros(3), np.zeros(3)) and kf.updates == 1
    with pytest.raises(ValueError, match="event kinds"):
        kf.run(np.array([0, 7]), np.array([1, 2]))
    kf.P[0, 0] = np.nan
    kf.push_epoch(t + 5_000_000, np.zeros(6), 1)
    kf.push_epoch(t + 6_000_000, np.zeros(6), 1)
    with pytest.raises(np.linalg.LinAlgError):
        kf.imu(t + 6_000_000, np.zeros(3), np.zeros(3))
    with pytest.raises(np.linalg.LinAlgError):
        kf.run(np.array([IMU]), np.array([t + 6_000_000]))
