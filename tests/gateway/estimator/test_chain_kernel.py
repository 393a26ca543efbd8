"""The compiled epoch kernel (gateway/estimator/chain_kernel.py) against an independent computation
(Pinocchio's rnea through torques.py, LAPACK's lstsq, the numpy base-motion formula), and its
bits across batch sizes."""
from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

import robot_description as rd
from gateway.estimator import EstimatorModel, arm_reaction
from gateway.estimator.chain_kernel import WEIGHTS, EpochKernel, lstsq_min_norm, pack
from gateway.estimator.joint_filter import JointFilterSettings
from gateway.estimator.model import EstimatorModelError
from gateway.estimator.torques import (joint_accelerations_from_ft, joint_torques, joint_torques_simplified,
                                       sensor_jacobians)
from robot_description.generate import ArmSpec, LinkSpec, RobotSpec, urdf_text

REL = 1e-9          # agreement with Pinocchio, relative to the largest value compared
KAPPA = 1e6         # ... where the weighted J of every arm has a condition number up to this


def _asymmetric() -> rd.Robot:
    """Arms of 1, 6 and 3 joints, axes along x, y, z and two not along any axis."""
    spec = RobotSpec(name="asymmetric", mass_kg=900.0, inertia_kgm2=(700.0, 900.0, 1100.0), radius_m=1.2, arms=(
        ArmSpec("a_one", 10.0, (LinkSpec(1.5, 40.0, 10.0, axis=(0.0, 1.0, 0.0)),)),
        ArmSpec("b_six", 130.0, (LinkSpec(1.0, 50.0, 8.0, axis=(0.0, 0.0, 1.0)),
                                 LinkSpec(1.2, 40.0, 6.0, axis=(0.0, 1.0, 0.0)),
                                 LinkSpec(1.0, 30.0, 4.0, axis=(0.0, 1.0, 0.0)),
                                 LinkSpec(0.4, 10.0, 0.5, axis=(1.0, 0.0, 0.0)),
                                 LinkSpec(0.3, 8.0, 0.3, axis=(0.0, 1.0, 0.0)),
                                 LinkSpec(0.2, 5.0, 0.1, axis=(0.0, 0.0, 1.0)))),
        ArmSpec("c_three", -100.0, (LinkSpec(1.4, 60.0, 12.0, axis=(0.0, 0.0, 1.0)),
                                    LinkSpec(1.1, 30.0, 5.0, axis=(0.6, 0.0, 0.8)),
                                    LinkSpec(0.8, 20.0, 2.0, axis=(0.0, 0.6, -0.8)))),
    ))
    return rd.from_urdf_text(urdf_text(spec), name=spec.name)


def _massless_tips() -> rd.Robot:
    """three_arm with every arm's last link massless: its joint's column of J is exactly zero."""
    r = rd.load("three_arm")
    model = r.model.copy()
    for arm in r.arms:
        model.inertias[arm.joints[-1]] = pin.Inertia.Zero()
    return rd.Robot(name="three_arm_massless_tips", urdf=r.urdf, model=model, arms=r.arms,
                    imu_frame=r.imu_frame, r_imu=r.r_imu, R_imu=r.R_imu)


ROBOTS = {"paper_robot": lambda: rd.load("paper_robot"), "three_arm": lambda: rd.load("three_arm"),
          "asymmetric": _asymmetric, "massless_tips": _massless_tips}


LS = JointFilterSettings(enabled=False)
"""The joint filter off: least-squares accelerations and sensor-side torques, each epoch on its
own (what these tests compare with the reference forms; the filter has tests/.../test_joint_filter.py)."""


@pytest.fixture(scope="module", params=["paper_robot", "three_arm", "asymmetric"])
def case(request):
    model = EstimatorModel.from_robot(ROBOTS[request.param]())
    return model, EpochKernel(model, joint_filter=LS)


def _inputs(model: EstimatorModel, rng: np.random.Generator, B: int):
    n, p = model.n_joints, model.n_arms
    return (rng.uniform(-3.0, 3.0, (B, n)), rng.uniform(-1.0, 1.0, (B, n)), rng.normal(0.0, 50.0, (B, p, 6)),
            rng.normal(0.0, 30.0, (B, 6)), rng.normal(0.0, 0.05, (B, 3)))


def _rel(a, b) -> float:
    return float(np.abs(np.asarray(a) - b).max() / max(1.0, float(np.abs(b).max())))


def _conditions(model: EstimatorModel, q: np.ndarray, weights=WEIGHTS) -> np.ndarray:
    """Per arm, the condition number of the weighted J (Pinocchio's rnea; zero columns left out)."""
    data = model.data()
    data.q[:] = pin.neutral(model.robot.model)
    data.q[7:] = q
    wt = np.asarray(weights)[:, None]
    out = []
    for J in sensor_jacobians(model, data):
        s = np.linalg.svd(J * wt, compute_uv=False)
        out.append(s[0] / s[s > s[0] * 1e-12][-1])
    return np.array(out)


def _against_pinocchio(model, kernel, rng, epochs):
    """Worst relative errors of (simp, ddq, full), ddq and full scaled by the tolerance factor of
    each epoch, and the largest condition number seen."""
    data = model.data()
    worst, kappa = np.zeros(3), 0.0
    for q, dq, ft, thr, w_s in zip(*_inputs(model, rng, epochs)):
        simp, ddq, full, a_s, dw_s, _ = kernel.epoch(q, dq, ft, thr, w_s)
        r_simp = joint_torques_simplified(model, data, q, ft)
        r_ddq = joint_accelerations_from_ft(model, data, q, dq, ft, a_s, w_s, dw_s)
        r_full = joint_torques(model, data, q, dq, r_ddq, ft, a_s, w_s, dw_s)
        # Both sides solve the same least squares from J and w0 that differ at ~1e-16 (another
        # order of operations), so they agree only to ~cond(J_w) eps: REL holds up to a condition
        # of KAPPA, beyond which the allowance grows with it (the 6-joint arm reaches ~1e9 at
        # near-singular configurations, where ddq is noise times 1e9 anyway).
        k = float(_conditions(model, q).max())
        kappa = max(kappa, k)
        grow = max(1.0, k / KAPPA)
        worst = np.maximum(worst, [_rel(simp, r_simp), _rel(ddq, r_ddq) / grow, _rel(full, r_full) / grow])
    return worst, kappa


def test_agrees_with_pinocchio(case):
    model, kernel = case
    worst, kappa = _against_pinocchio(model, kernel, np.random.default_rng(11), 150)
    # observed: simp ~1e-15; ddq, full ~1e-13 (paper_robot, three_arm); asymmetric: ~5e-12 where
    # the condition is <= KAPPA, ~5e-9 (unscaled) at the worst epoch drawn, of condition 1.2e9
    assert (worst <= REL).all(), f"relative errors simp, ddq, full: {worst}, largest condition {kappa:.3g}"


def test_rank_deficient_arm_gives_the_minimum_norm_solution():
    # a massless last link: the weighted J of every arm has an exactly zero column; lstsq's
    # minimum-norm solution gives that joint ddq = 0, and so must the kernel (no inf, no blow-up)
    model = EstimatorModel.from_robot(_massless_tips())
    kernel = EpochKernel(model, joint_filter=LS)
    worst, _ = _against_pinocchio(model, kernel, np.random.default_rng(12), 40)
    assert (worst <= REL).all(), f"relative errors simp, ddq, full: {worst}"
    q, dq, ft, thr, w_s = _inputs(model, np.random.default_rng(13), 50)
    ddq = kernel.batch(q, dq, ft, thr, w_s)[1]
    tips = [a.columns[-1] for a in model.arms]
    assert np.isfinite(ddq).all() and (ddq[:, tips] == 0.0).all()


def test_custom_weights_and_the_default_weights():
    # the defaults: _against_pinocchio compares the kernel's with joint_accelerations_from_ft's
    assert WEIGHTS == (4.0, 4.0, 4.0, 40.0, 40.0, 40.0)
    model = EstimatorModel.from_robot(rd.load("three_arm"))
    wt = np.array([1.0, 2.0, 3.0, 10.0, 20.0, 30.0])
    kernel = EpochKernel(model, weights=wt, joint_filter=LS)
    data = model.data()
    for q, dq, ft, thr, w_s in zip(*_inputs(model, np.random.default_rng(14), 20)):
        _, ddq, _, a_s, dw_s, _ = kernel.epoch(q, dq, ft, thr, w_s)
        assert _rel(ddq, joint_accelerations_from_ft(model, data, q, dq, ft, a_s, w_s, dw_s, weights=wt)) <= REL


def test_base_motion_matches_the_numpy_formula(case):
    model, kernel = case
    q, dq, ft, thr, w_s = _inputs(model, np.random.default_rng(15), 500)
    _, _, _, a_s, dw_s, arm_w = kernel.batch(q, dq, ft, thr, w_s)
    ref_w = -(ft.reshape(len(ft), -1) @ model.A_s_all.T)
    I_s = model.inertia_s
    ref_a = (thr[:, :3] + ref_w[:, :3]) / model.mass_s
    rhs = (thr[:, 3:] + ref_w[:, 3:]) - np.cross(w_s, w_s @ I_s.T)
    ref_dw = np.linalg.solve(I_s, rhs.T).T
    for got, ref in ((arm_w, ref_w), (arm_w, arm_reaction(model, ft)), (a_s, ref_a), (dw_s, ref_dw)):
        assert _rel(got, ref) <= 1e-13


@pytest.mark.parametrize("joint_filter", [False, True], ids=["least-squares", "joint-filter"])
def test_same_bits_whatever_the_batch(case, joint_filter):
    model, kernel = case
    if joint_filter:                       # state carried from epoch to epoch, in order
        kernel = EpochKernel(model)
    rng = np.random.default_rng(16)
    N = 2345
    x = _inputs(model, rng, N)
    kernel.reset()
    whole = kernel.batch(*x)
    kernel.reset()
    chunks = [kernel.batch(*(a[lo:lo + 1000] for a in x)) for lo in range(0, N, 1000)]
    cuts = np.sort(rng.choice(np.arange(1, N), 40, replace=False))
    kernel.reset()
    pieces = [kernel.batch(*(a[lo:hi] for a in x)) for lo, hi in zip(np.r_[0, cuts], np.r_[cuts, N])]
    kernel.reset()
    singles = [kernel.epoch(*(a[i] for a in x)) for i in range(N)]
    out = kernel.outputs()
    kernel.reset()
    into = [[o.copy() for o in kernel.epoch(*(a[i] for a in x), out=out)] for i in range(N)]
    for k in range(6):
        assert np.array_equal(whole[k], np.concatenate([c[k] for c in chunks]))
        assert np.array_equal(whole[k], np.concatenate([c[k] for c in pieces]))
        assert np.array_equal(whole[k], np.stack([s[k] for s in singles]))
        assert np.array_equal(whole[k], np.stack([s[k] for s in into]))
    assert all(np.isfinite(w).all() for w in whole)


@pytest.mark.parametrize("shape", [(6, 1), (6, 2), (6, 3), (6, 6), (4, 3), (9, 5)])
def test_lstsq_min_norm_matches_lapack(shape):
    rng = np.random.default_rng(17)
    m, n = shape
    eps = np.finfo(float).eps
    for trial in range(200):
        a = rng.normal(size=shape) * 10.0 ** rng.uniform(-3, 3, size=n)
        if trial % 4 == 1 and m == 6:
            a[[2, 3, 4]] = 0.0                     # a planar arm: three channels see nothing
        if trial % 4 == 2 and n > 1:
            a[:, -1] = 0.0                         # a column exactly zero
        if trial % 4 == 3 and n > 1:
            a[:, -1] = 4.0 * a[:, 0]               # a column exactly dependent
        b = a @ rng.normal(size=n) + rng.normal(size=m) * 10.0 ** rng.uniform(-3, 3)
        ref = np.linalg.lstsq(a, b, rcond=None)[0]
        # the least-squares perturbation bound (Golub & Van Loan 5.3.8) on the part solved for:
        # eps (kappa + kappa^2 |r| / (|A| |x|)), times a small constant
        s = np.linalg.svd(a, compute_uv=False)
        kappa = s[0] / s[s > s[0] * 1e-12][-1]
        eta = np.linalg.norm(a @ ref - b) / (s[0] * np.linalg.norm(ref))
        bound = 20 * m * eps * (kappa + kappa ** 2 * eta)
        for qr in (True, False):                   # QR (and its fallback), the Jacobi SVD alone
            err = np.linalg.norm(lstsq_min_norm(a, b, qr=qr) - ref) / np.linalg.norm(ref)
            assert err <= bound, (trial, qr, err, kappa, eta)


def test_pack_pads_arms_of_different_lengths():
    model = EstimatorModel.from_robot(_asymmetric())
    arrays = pack(model)
    assert arrays.arm_n.tolist() == [1, 6, 3] and arrays.arm_col.tolist() == [0, 1, 7]
    assert arrays.link.shape == (3, 6, 25) and (arrays.link[0, 1:] == 0.0).all()
    assert arrays.link[:, 0, 12].tolist() == [40.0, 50.0, 60.0]            # first links' masses, kg
    assert not arrays.link.flags.writeable


def test_bad_inputs_are_refused():
    model = EstimatorModel.from_robot(rd.load("paper_robot"))
    kernel = EpochKernel(model)
    n = model.n_joints
    with pytest.raises(ValueError):
        kernel.epoch(np.zeros(n + 1), np.zeros(n), np.zeros((2, 6)), np.zeros(6), np.zeros(3))
    with pytest.raises(ValueError):
        kernel.epoch(np.zeros(n), np.zeros(n), np.zeros((3, 6)), np.zeros(6), np.zeros(3))
    with pytest.raises(ValueError):
        kernel.batch(np.zeros((5, n)), np.zeros((4, n)), np.zeros((5, 2, 6)), np.zeros((5, 6)), np.zeros((5, 3)))
    with pytest.raises(ValueError):
        EpochKernel(model, weights=(1.0, 2.0))
    with pytest.raises(EstimatorModelError):
        spec = RobotSpec(name="seven", mass_kg=900.0, inertia_kgm2=(700.0, 900.0, 1100.0), radius_m=1.2,
                         arms=(ArmSpec("a", 0.0, tuple(LinkSpec(0.5, 10.0, 1.0) for _ in range(7))),))
        pack(EstimatorModel.from_robot(rd.from_urdf_text(urdf_text(spec), name="seven")))
