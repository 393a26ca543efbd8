"""PNG figures of a truth trace, after the paper's: trajectories, end-effector error, commanded
vs actual joint torques and thruster wrench. matplotlib with the Agg backend (no display)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .truth import Trace

AXES = ["fx [N]", "fy [N]", "fz [N]", "mx [N m]", "my [N m]", "mz [N m]"]


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def trajectories(tr: Trace, path: Path) -> Path:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 6))
    base = tr["q"][:, :2]
    ax.plot(base[:, 0], base[:, 1], "k-", lw=2, label="spacecraft C")
    for k, arm in enumerate(tr.meta["arms"]):
        ax.plot(tr["ee"][:, k, 0], tr["ee"][:, k, 1], lw=1.5, label=f"{arm} end effector")
        ax.plot(tr["ee_des"][:, k, 0], tr["ee_des"][:, k, 1], "--", lw=1, label=f"{arm} desired")
    sc = tr.meta.get("target_center_m")
    if sc:
        th = np.linspace(0, 2 * np.pi, 200)
        r = tr.meta["target_radius_m"]
        ax.plot(sc[0] + r * np.cos(th), sc[1] + r * np.sin(th), ":", color="gray", label="target rim")
    th = np.linspace(0, 2 * np.pi, 100)
    ax.plot(base[0, 0] + 2.1 * np.cos(th), base[0, 1] + 2.1 * np.sin(th), color="0.6", lw=0.8)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"Trajectories ({tr.meta['scenario']})")
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def ee_error(traces: dict[str, Trace], path: Path) -> Path:
    plt = _plt()
    first = next(iter(traces.values()))
    arms = first.meta["arms"]
    fig, axs = plt.subplots(len(arms), 1, figsize=(8, 2.4 * len(arms)), sharex=True, squeeze=False)
    for label, tr in traces.items():
        e = np.linalg.norm(tr["ee"] - tr["ee_des"], axis=2)
        for k, arm in enumerate(arms):
            axs[k, 0].plot(tr["t_s"], e[:, k], label=label)
    for k, arm in enumerate(arms):
        axs[k, 0].set_ylabel(f"{arm} error [m]")
        axs[k, 0].grid(alpha=0.3)
        axs[k, 0].legend(fontsize=8)
    axs[-1, 0].set_xlabel("time [s]")
    fig.suptitle("End-effector position error")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def joint_torques(tr: Trace, path: Path, estimates: dict[str, np.ndarray] | None = None) -> Path:
    """Commanded and actual torque of every joint; optional estimates (N, n) by label."""
    plt = _plt()
    names = tr.meta["joints"]
    n = len(names)
    cols = 2 if n > 1 else 1
    rows = (n + cols - 1) // cols
    fig, axs = plt.subplots(rows, cols, figsize=(6 * cols, 2.4 * rows), sharex=True, squeeze=False)
    t = tr["t_s"]
    for j, name in enumerate(names):
        ax = axs[j // cols, j % cols]
        ax.plot(t, tr["tau_cmd"][:, j], lw=1, label="commanded")
        ax.plot(t, tr["tau_act"][:, j], lw=1, label="actual")
        for label, est in (estimates or {}).items():
            ax.plot(t[: len(est)], est[:, j], lw=0.8, ls="--", label=label)
        ax.set_title(name, fontsize=9)
        ax.set_ylabel("N m")
        ax.grid(alpha=0.3)
    for j in range(n, rows * cols):
        axs[j // cols, j % cols].axis("off")
    axs[0, 0].legend(fontsize=7)
    for ax in axs[-1]:
        ax.set_xlabel("time [s]")
    fig.suptitle("Joint torques: commanded vs actual (motor minus friction)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def thruster_wrench(tr: Trace, path: Path, estimates: dict[str, np.ndarray] | None = None) -> Path:
    """Commanded and actual thruster force and moment (body frame, about C), 6 axes."""
    plt = _plt()
    fig, axs = plt.subplots(3, 2, figsize=(12, 7.5), sharex=True)
    t = tr["t_s"]
    for i in range(6):
        ax = axs[i % 3, i // 3]
        ax.plot(t, tr["thr_act"][:, i], lw=0.6, color="tab:orange", label="actual")
        ax.plot(t, tr["thr_cmd"][:, i], lw=1.2, color="tab:blue", label="commanded")
        for label, est in (estimates or {}).items():
            ax.plot(t[: len(est)], est[:, i], lw=0.8, ls="--", label=label)
        ax.set_ylabel(AXES[i])
        ax.grid(alpha=0.3)
    axs[0, 0].legend(fontsize=7)
    axs[-1, 0].set_xlabel("time [s]")
    axs[-1, 1].set_xlabel("time [s]")
    fig.suptitle("Thruster force and moment (body frame, about C): commanded vs actual")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
