"""Contact at an end effector: how soon the gateway flags it, how well it measures it, and that it
flags nothing else.

``python -m benchmarks.bench_contact [--quick]`` (``bsc bench --only contact``: the rows; opt-in,
a few minutes).

Each case is a simulated session (lockstep: the firmware's CAN frames through the gateway's
session, as ``bsc demo`` runs it) with one ``[[contact]]`` table: a force of 5-50 N along an
inertial axis on one arm's end effector from 3.0 s for 1.5 s (20 ms ramps). Per case: when the
arm's contact flag rose after the onset, when it dropped after the end, the published contact
wrench against the truth while flagged (RMS, force N, moment about the end effector N m), and
the touched arm's joint torques during the contact (worst NRMSE against the joint's peak over
the session). The healthy sessions (no contact: capture and three_arm, seeds 1-3; the sensors at
four times their noise; a model 5 % off) must flag nothing.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

SIZES_N = (5.0, 10.0, 20.0, 50.0)
AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
ROBOTS = (("capture", "arm0"), ("three_arm", "center"))
ONSET_S, LENGTH_S, DURATION_S = 3.0, 1.5, 6.0
HEALTHY = (("capture", 1, {}, False), ("capture", 2, {}, False), ("capture", 3, {}, False),
           ("three_arm", 1, {}, False), ("three_arm", 2, {}, False), ("three_arm", 3, {}, False),
           ("capture", 1, {"noise.scale": 4.0}, False), ("three_arm", 1, {"noise.scale": 4.0}, False),
           ("capture", 1, {}, True), ("three_arm", 1, {}, True))


def session(name: str, seed: int, contact: list[dict], over: dict | None = None, wrong: bool = False) -> dict:
    """One lockstep session; its ``harness.demo.contacts`` report plus ``touched_worst_nrmse``
    (per table: the touched arm's worst joint during the contact)."""
    import robot_description as rd
    from harness import demo
    from simulator import scenario

    sc = scenario.load(name, {"seed": seed, "duration_s": DURATION_S, **(over or {})})
    sc.data["contact"] = contact
    robot = rd.load(sc.robot)
    model = rd.perturbed(robot, 0.05, seed=1) if wrong else None
    trace, est, _ = demo.run_offline(sc, model_robot=model)
    rep = demo.contacts(trace, est, robot, contact)
    t, tau = trace.arrays["t_s"], trace.arrays["tau_act"]
    peak = np.abs(tau).max(axis=0)
    cols, col = {}, 0
    for a in robot.arms:
        cols[a.name] = slice(col, col + a.n)
        col += a.n
    for row in rep["contacts"]:
        m = (t >= row["onset_s"]) & (t < row["end_s"])
        sl = cols[row["arm"]]
        err = np.sqrt(np.nanmean((est.full[m, sl] - tau[m, sl]) ** 2, axis=0)) / peak[sl]
        row["touched_worst_nrmse"] = round(float(err.max()), 4)
    return rep


def study(quick: bool = False) -> tuple[list[dict], list[dict], float]:
    t0 = time.perf_counter()
    rows = []
    sizes = (10.0, 20.0) if quick else SIZES_N
    axes = ("y",) if quick else tuple(AXES)
    for name, arm in ROBOTS:
        for size in sizes:
            for ax in axes:
                table = {"arm": arm, "onset_s": ONSET_S, "duration_s": LENGTH_S,
                         "force_n": [size * v for v in AXES[ax]]}
                rep = session(name, 1, [table])
                rows.append({"scenario": name, "size_n": size, "axis": ax, **rep["contacts"][0],
                             "false_contact_s": sum(rep["false_contact_s"].values())})
    healthy = []
    for name, seed, over, wrong in (HEALTHY[:1] + HEALTHY[3:4] if quick else HEALTHY):
        rep = session(name, seed, [], over, wrong)
        what = ", ".join([f"seed {seed}"] + [f"{k} {v:g}" for k, v in over.items()]
                         + (["model 5 % off"] if wrong else []))
        healthy.append({"scenario": name, "case": what, "false_contact_s": sum(rep["false_contact_s"].values())})
    return rows, healthy, time.perf_counter() - t0


def table(rows: list[dict], healthy: list[dict]) -> str:
    out = [f"{'scenario':10s} {'arm':7s} {'force':>7s} {'axis':4s} {'flagged after':>13s} {'released after':>14s} "
           f"{'force err':>9s} {'moment err':>10s} {'arm worst joint':>15s} {'false':>6s}"]

    def ms(x):
        return "never" if x is None else f"{1000 * x:.0f} ms"

    for r in rows:
        fe = "-" if r["force_rms_error_n"] is None else f"{r['force_rms_error_n']:.2f} N"
        me = "-" if r["moment_rms_error_nm"] is None else f"{r['moment_rms_error_nm']:.2f} N m"
        worst = 100 * r["touched_worst_nrmse"]
        out.append(f"{r['scenario']:10s} {r['arm']:7s} {r['size_n']:5.0f} N {r['axis']:4s} "
                   f"{ms(r['flagged_after_s']):>13s} {ms(r['released_after_s']):>14s} {fe:>9s} {me:>10s} "
                   f"{worst:14.2f}% {r['false_contact_s']:5.2f}s")
    out.append("")
    out.append("healthy sessions (no contact):")
    for h in healthy:
        out.append(f"  {h['scenario']:10s} {h['case']:32s} flagged {h['false_contact_s']:.2f} s")
    return "\n".join(out)


def figures(quick: bool = False) -> list[dict]:
    """The suite's rows (``bsc bench --only contact``)."""
    from benchmarks.anchors import row

    rows, healthy, wall = study(quick)
    out = []
    for name, _ in ROBOTS:
        mine = [r for r in rows if r["scenario"] == name]
        found = [r for r in mine if r["flagged_after_s"] is not None]
        smallest = min((r["size_n"] for r in mine if all(
            x["flagged_after_s"] is not None for x in mine if x["size_n"] == r["size_n"])), default=None)
        out.append(row(f"{name}: contacts flagged", len(found), f"of {len(mine)}",
                       note=f"{', '.join(f'{s:g}' for s in sorted({r['size_n'] for r in mine}))} N along the "
                            f"inertial axes; every axis from {smallest:g} N" if smallest else "none on every axis"))
        if found:
            delays = sorted(r["flagged_after_s"] for r in found)
            out.append(row(f"{name}: time to flag a contact, median", round(1000 * delays[len(delays) // 2]), "ms",
                           note=f"worst {1000 * delays[-1]:.0f} ms"))
            out.append(row(f"{name}: contact force error, worst RMS", max(r["force_rms_error_n"] for r in found), "N"))
    false = sum(h["false_contact_s"] for h in healthy) + sum(r["false_contact_s"] for r in rows)
    out.append(row("false contacts", round(false, 3), "s flagged", target="0", ok=false == 0.0,
                   note=f"{len(healthy)} healthy sessions and the contact sessions' other arms; {wall:.0f} s"))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="two sizes, one axis, two healthy sessions")
    a = ap.parse_args()
    rows, healthy, wall = study(a.quick)
    print(table(rows, healthy))
    print(f"({wall:.0f} s)")


if __name__ == "__main__":
    main()
