"""Running estimates of the live monitor: pure, no I/O, fed one sample at a time.

Each tracker forgets exponentially with time constant ``tau_s`` in SENSOR time (the samples'
``t_ns``), and weighs each sample by the time it stands for (capped), so the estimates do not
depend on the publication rate. ``weight_s`` says how many (weighted) seconds of data back an
estimate; rules see an estimate only once that reaches ``min_weight_s``.

- :class:`JointTracker` (one joint): ``r = commanded - estimated`` (the friction that opposed the
  motion, docs/method.md section 3); ``friction_nm``/``viscous_nms``/``offset_nm`` from a weighted
  least-squares fit ``r = Fc sign(dq) + Fv dq + c`` over moving samples (the same model as
  ``bsc analyze``, gateway/analysis/session.py); ``residual_nm`` the running mean |r|;
  ``efficiency`` estimated / commanded (least squares through 0).
- :class:`AxisTracker` (one thruster axis): ``efficiency`` (est = eta cmd + c), ``offset``,
  ``residual`` running mean |est - cmd|.
- :class:`DeviceTracker` / bus load: from the drivers' health reports.
"""
from __future__ import annotations

import math

import numpy as np

MAX_SAMPLE_WEIGHT_S = 0.1      # a gap longer than this counts as this much data, not more
AXIS_MIN_CMD_RMS = 10.0        # N or N m, as in bsc analyze


class EwLeastSquares:
    """Exponentially weighted least squares ``y ~ x . beta`` (normal equations, time forgetting)."""

    def __init__(self, n: int, tau_s: float):
        self.tau_s = tau_s
        self.A = np.zeros((n, n))
        self.b = np.zeros(n)
        self.yy = 0.0
        self.weight_s = 0.0
        self.t_ns: int | None = None

    def decay_to(self, t_ns: int) -> None:
        if self.t_ns is not None and t_ns > self.t_ns:
            f = math.exp(-(t_ns - self.t_ns) / 1e9 / self.tau_s)
            self.A *= f
            self.b *= f
            self.yy *= f
            self.weight_s *= f
        if self.t_ns is None or t_ns > self.t_ns:
            self.t_ns = t_ns

    def add(self, x: np.ndarray, y: float, w_s: float) -> None:
        self.A += w_s * np.outer(x, x)
        self.b += w_s * y * x
        self.yy += w_s * y * y
        self.weight_s += w_s

    def solve(self) -> np.ndarray | None:
        if self.weight_s <= 0:
            return None
        try:
            if np.linalg.cond(self.A) > 1e10:
                return None
            return np.linalg.solve(self.A, self.b)
        except np.linalg.LinAlgError:
            return None


class _Ewma:
    def __init__(self, tau_s: float):
        self.tau_s, self.value, self.weight_s, self.t_ns = tau_s, 0.0, 0.0, None

    def add(self, x: float, t_ns: int, w_s: float) -> None:
        if self.t_ns is not None and t_ns > self.t_ns:
            f = math.exp(-(t_ns - self.t_ns) / 1e9 / self.tau_s)
            self.weight_s *= f
        self.t_ns = t_ns if self.t_ns is None else max(self.t_ns, t_ns)
        total = self.weight_s + w_s
        if total > 0:
            self.value += (x - self.value) * (w_s / total)
        self.weight_s = total


class JointTracker:
    def __init__(self, tau_s: float = 20.0, v_min_rad_s: float = 0.02, limit_nm: float | None = None):
        self.v_min = v_min_rad_s
        self.limit_nm = limit_nm
        self.fric = EwLeastSquares(3, tau_s)
        self.eff = EwLeastSquares(1, tau_s)
        self.res = _Ewma(tau_s)
        self.pos = _Ewma(tau_s)        # weight of moving samples in each direction
        self.neg = _Ewma(tau_s)
        self.last_t_ns: int | None = None
        self.samples = 0

    def add(self, t_ns: int, commanded_nm: float, estimated_nm: float, rate_rad_s: float) -> None:
        w = (MAX_SAMPLE_WEIGHT_S if self.last_t_ns is None
             else min(MAX_SAMPLE_WEIGHT_S, max(0.0, (t_ns - self.last_t_ns) / 1e9)))
        if self.last_t_ns is not None and t_ns <= self.last_t_ns:
            return                           # out of order or duplicate: the fit wants time order
        self.last_t_ns = t_ns
        self.samples += 1
        r = commanded_nm - estimated_nm
        self.res.add(abs(r), t_ns, w)
        self.eff.decay_to(t_ns)
        self.eff.add(np.array([commanded_nm]), estimated_nm, w)
        self.fric.decay_to(t_ns)
        moving = abs(rate_rad_s) > self.v_min
        self.pos.add(1.0 if moving and rate_rad_s > 0 else 0.0, t_ns, w)
        self.neg.add(1.0 if moving and rate_rad_s < 0 else 0.0, t_ns, w)
        if moving:
            self.fric.add(np.array([math.copysign(1.0, rate_rad_s), rate_rad_s, 1.0]), r, w)

    def metrics(self, min_weight_s: float = 2.0) -> dict[str, float]:
        nan = float("nan")
        out = {"residual_nm": self.res.value if self.res.weight_s >= min_weight_s else nan,
               "friction_nm": nan, "viscous_nms": nan, "offset_nm": nan, "efficiency": nan,
               "friction_fraction": nan, "weight_s": self.fric.weight_s}
        # Coulomb friction needs motion both ways (else it is confounded with the offset)
        both = min(self.pos.value, self.neg.value) * self.pos.weight_s
        if self.fric.weight_s >= min_weight_s and both >= 0.1 * min_weight_s:
            beta = self.fric.solve()
            if beta is not None:
                out["friction_nm"], out["viscous_nms"], out["offset_nm"] = (float(x) for x in beta)
                if self.limit_nm:
                    out["friction_fraction"] = out["friction_nm"] / self.limit_nm
        if self.eff.weight_s >= min_weight_s and self.eff.A[0, 0] > 0:
            out["efficiency"] = float(self.eff.b[0] / self.eff.A[0, 0])
        return out


class AxisTracker:
    def __init__(self, tau_s: float = 20.0, min_cmd_rms: float = AXIS_MIN_CMD_RMS):
        self.fit = EwLeastSquares(2, tau_s)
        self.res = _Ewma(tau_s)
        self.min_cmd_rms = min_cmd_rms
        self.last_t_ns: int | None = None
        self.samples = 0

    def add(self, t_ns: int, estimated: float, commanded: float) -> None:
        if self.last_t_ns is not None and t_ns <= self.last_t_ns:
            return
        w = MAX_SAMPLE_WEIGHT_S if self.last_t_ns is None else min(MAX_SAMPLE_WEIGHT_S, (t_ns - self.last_t_ns) / 1e9)
        self.last_t_ns = t_ns
        self.samples += 1
        self.res.add(abs(estimated - commanded), t_ns, w)
        self.fit.decay_to(t_ns)
        self.fit.add(np.array([commanded, 1.0]), estimated, w)

    def metrics(self, min_weight_s: float = 2.0) -> dict[str, float]:
        nan = float("nan")
        out = {"efficiency": nan, "offset": nan, "cmd_rms": nan,
               "residual": self.res.value if self.res.weight_s >= min_weight_s else nan,
               "weight_s": self.fit.weight_s}
        W = self.fit.weight_s
        if W >= min_weight_s:
            mean_sq = self.fit.A[0, 0] / W
            mean = self.fit.A[0, 1] / W
            out["cmd_rms"] = math.sqrt(max(0.0, mean_sq))
            if out["cmd_rms"] >= self.min_cmd_rms and mean_sq - mean * mean > 1e-9:
                beta = self.fit.solve()
                if beta is not None:
                    out["efficiency"], out["offset"] = float(beta[0]), float(beta[1])
        return out


class DeviceTracker:
    """Staleness and loss rate of one device from its DeviceHealth snapshots."""

    def __init__(self):
        self.first_t_ns: int | None = None
        self.prev: tuple[int, int] | None = None     # (samples, lost) of the previous report
        self.staleness_s = float("nan")
        self.loss_rate = float("nan")
        self.samples = 0
        self.lost = 0
        self.t_ns = 0

    def add(self, h) -> None:
        self.first_t_ns = h.t_ns if self.first_t_ns is None else self.first_t_ns
        self.t_ns = h.t_ns
        ref = h.last_t_ns if h.last_t_ns > 0 else self.first_t_ns
        self.staleness_s = max(0.0, (h.t_ns - ref) / 1e9)
        if self.prev is not None:
            ds, dl = h.samples - self.prev[0], h.lost - self.prev[1]
            if ds + dl > 0 and ds >= 0 and dl >= 0:
                self.loss_rate = dl / (ds + dl)
            elif ds + dl == 0:
                self.loss_rate = float("nan")
        self.prev = (h.samples, h.lost)
        self.samples, self.lost = h.samples, h.lost

    def metrics(self) -> dict[str, float]:
        return {"staleness_s": self.staleness_s, "loss_rate": self.loss_rate,
                "samples": float(self.samples), "lost": float(self.lost)}
