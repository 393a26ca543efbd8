"""Angular acceleration / thruster moment filters: derivative filters, Kalman filters, trade-off."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from gateway.estimator.filters import (
    PAPER_INERTIA, LowPassDifferentiator, RotationalKF, TranslationalKF, gyro_rate_sigma,
    lowpass_derivative, lowpass_differentiator_coefficients, measure_tradeoff, rotation_scenario,
    savgol_derivative,
)

FS = 1000.0


def test_gyro_sigma_from_arw_by_hand():
    # 0.07 deg/sqrt(h) = 0.07/60 deg/sqrt(s) = 2.0362e-5 rad/sqrt(s); * sqrt(1000 Hz)
    assert gyro_rate_sigma(0.07, 1000.0) == pytest.approx(6.439e-4, rel=1e-3)


@pytest.mark.parametrize("fc", [1.0, 5.0, 20.0])
def test_lowpass_differentiator_response(fc):
    b, a = lowpass_differentiator_coefficients(fc, FS)
    f = np.array([fc / 100, fc])
    _, H = signal.freqz(b, a, worN=f, fs=FS)
    ideal = 2 * np.pi * f
    assert abs(H[0]) / ideal[0] == pytest.approx(1.0, abs=1e-3)          # a derivative well below fc
    assert abs(H[1]) / ideal[1] == pytest.approx(math.sqrt(0.5), abs=1e-3)  # -3 dB at the documented cutoff


def test_lowpass_differentiator_live_equals_batch_and_tracks_a_ramp():
    t = np.arange(3000) / FS
    x = np.stack([0.3 * t, -0.1 * t + 2.0, np.sin(t)], axis=1)
    batch = lowpass_derivative(x, FS, 5.0)
    live = LowPassDifferentiator(5.0, FS)
    stream = np.array([live.update(xk) for xk in x])
    np.testing.assert_allclose(stream, batch, atol=1e-12)
    np.testing.assert_allclose(batch[-1, :2], [0.3, -0.1], atol=1e-6)    # ramp slope after settling
    assert live.group_delay_s == pytest.approx(2 * math.sqrt(0.5) / (2 * math.pi * 5.0))


def test_savgol_derivative_exact_on_a_quadratic():
    t = np.arange(500) / FS
    x = 3.0 * t ** 2 - t
    np.testing.assert_allclose(savgol_derivative(x, FS, 0.05), 6.0 * t - 1.0, atol=1e-9)


@pytest.fixture(scope="module")
def scenario():
    return rotation_scenario(duration_s=6.0, step_period_s=1.5, seed=1)


def test_rotational_kf_beats_raw_difference_by_a_large_factor(scenario):
    sc = scenario
    sigma = gyro_rate_sigma(0.07, FS)
    w, tau, dw = RotationalKF(sc.inertia, FS, gyro_sigma=sigma, torque_walk=100.0).run(sc.gyro, sc.tau_arms)
    k0 = int(FS)
    raw_dw = np.diff(sc.gyro, axis=0) * FS
    raw_tau = raw_dw @ sc.inertia.T + np.cross(sc.gyro[1:], sc.gyro[1:] @ sc.inertia.T) - sc.tau_arms[1:]
    def rms(e):
        return float(np.sqrt(np.mean(e[k0:] ** 2)))

    err_raw = rms(raw_tau - sc.tau_thr[1:])
    err_kf = rms(tau - sc.tau_thr)
    assert err_raw > 2000.0                      # ~ I sigma sqrt(2) fs: thousands of N m
    assert err_raw / err_kf > 100.0
    assert rms(raw_dw - sc.dw[1:]) / rms(dw - sc.dw) > 100.0
    assert rms(w - sc.w) < sigma                  # the filtered rate beats the gyro too


def test_rotational_kf_converges_on_clean_data(scenario):
    """No noise: away from the jumps the estimate settles on the true moment (model is right)."""
    sc = scenario
    _, tau, _ = RotationalKF(sc.inertia, FS, gyro_sigma=6.4e-4, torque_walk=100.0).run(sc.w, sc.tau_arms)
    k = int(1.4 * FS)                             # 0.4 s after the first jump, before the next
    np.testing.assert_allclose(tau[k], sc.tau_thr[k], atol=1.0)


def test_translational_kf_recovers_a_force_step():
    rng = np.random.default_rng(0)
    m, N = 2400.0, 4000
    f_thr = np.where(np.arange(N)[:, None] < 2000, [10.0, -5.0, 0.0], [-20.0, 0.0, 8.0])
    f_arms = 50.0 * np.sin(np.arange(N) / FS)[:, None] * np.ones(3)
    sigma = 1e-3
    acc = (f_thr + f_arms) / m + sigma * rng.standard_normal((N, 3))
    # per-sample force noise m sigma = 2.4 N; walk 5 N/sqrt(s): ~15 ms time constant, ~0.6 N noise
    f_hat, a_hat = TranslationalKF(m, FS, accel_sigma=sigma, force_walk=5.0).run(acc, f_arms)
    np.testing.assert_allclose(f_hat[1500:2000].mean(axis=0), f_thr[0], atol=0.3)
    np.testing.assert_allclose(f_hat[3500:].mean(axis=0), f_thr[-1], atol=0.3)
    assert np.std(a_hat[3000:] - (f_thr + f_arms)[3000:] / m) < 0.5 * sigma


def test_tradeoff_table(scenario):
    sc = scenario
    rows = measure_tradeoff(sc, cutoffs_hz=(2.0,), savgol_windows_s=(0.2,), torque_walks=(30.0,))
    by = {r.method: r for r in rows}
    raw = by["raw difference"]
    sigma = gyro_rate_sigma(0.07, FS)
    theory = math.sqrt(np.mean(np.diag(PAPER_INERTIA) ** 2)) * sigma * math.sqrt(2) * FS
    assert raw.noise_rms_nm == pytest.approx(theory, rel=0.05)
    assert raw.rise90_s <= 0.002
    kf = by["rotational KF"]
    assert kf.noise_rms_nm < raw.noise_rms_nm / 300
    lp = by["low-pass differentiator"]
    assert lp.rise90_s > 0.1 and kf.rise90_s > 0.1                     # smoothing costs lag
    assert not by["Savitzky-Golay (offline)"].causal
