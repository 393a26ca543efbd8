"""Human outputs of ``bsc analyze``: a text summary, and a Markdown report with PNG trend plots."""
from __future__ import annotations

import math
from pathlib import Path

from .change import SeriesResult, Track

PLOTS = {"friction.png": ("coulomb_nm", "Coulomb friction per joint", "N m"),
         "thrusters.png": ("efficiency", "Thruster efficiency per axis (estimated / commanded)", "-"),
         "ft_offsets.png": ("offset_nm", "Joint residual offset (F/T bias indicator)", "N m"),
         "momentum.png": ("quiet_offset", "Thruster wrench estimate with no thruster firing (F/T vs IMU)", "N, N m")}


def _fmt(x: float, spec: str = ".1f") -> str:
    return format(x, spec) if isinstance(x, float) and math.isfinite(x) else "-"


def summary_text(result: SeriesResult, skipped: list[str] = ()) -> str:
    ss = result.sessions
    out = [f"{len(ss)} session(s), in time order: {ss[0].name} .. {ss[-1].name}"
           + (f"; {len(skipped)} skipped" if skipped else "")]
    for reason in skipped:
        out.append(f"  skipped: {reason}")
    joints = sorted({j for s in ss for j in s.joints})
    if joints:
        out.append("")
        out.append("friction per joint, Coulomb N m (viscous N m s/rad) [offset N m]:")
        out.append(f"  {'session':<22}" + "".join(f"{j:>24}" for j in joints))
        for s in ss:
            row = ""
            for j in joints:
                f = s.joints.get(j)
                cell = (f"{_fmt(f.coulomb_nm)} ({_fmt(f.viscous_nms)}) [{_fmt(f.offset_nm)}]"
                        if f and f.identifiable else "not identifiable")
                row += f"{cell:>24}"
            out.append(f"  {s.name:<22}" + row)
    axes = [a for a in ("fx", "fy", "fz", "mx", "my", "mz") if any(a in s.axes for s in ss)]
    if axes:
        out.append("")
        out.append("thruster efficiency per axis [offset with no thruster firing, N or N m]:")
        out.append(f"  {'session':<22}" + "".join(f"{a:>16}" for a in axes))
        for s in ss:
            row = "".join(f"{_fmt(s.axes[a].efficiency, '.3f') + ' [' + _fmt(s.axes[a].quiet_offset) + ']':>16}"
                          if a in s.axes else f"{'-':>16}" for a in axes)
            out.append(f"  {s.name:<22}" + row)
    touched = [(s, arm, c) for s in ss for arm, c in sorted(s.contacts.items())]
    if touched:
        out.append("")
        out.append("contacts (a wrench on an arm that the model does not know, JointEfforts.contact):")
        for s, arm, c in touched:
            out.append(f"  {s.name:<22} {arm:<10} {int(c['count'])} contact(s), {c['seconds']:.2f} s in all, "
                       f"up to {c['max_force_n']:.1f} N")
    out.append("")
    if not result.findings:
        out.append("alerts: none")
    else:
        out.append(f"alerts ({len(result.findings)}):")
        for f in result.findings:
            out.append(f"  {f.session:<22} {f.state:<7} {f.severity:<8} {f.kind:<8} {f.target:<8} "
                       f"[{f.rule}] {f.message}")
    return "\n".join(out)


def _plot(result: SeriesResult, metric: str, title: str, unit: str, path: Path) -> bool:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tracks: list[Track] = [t for t in result.tracks if t.detector.metric == metric
                           and any(math.isfinite(v) for v in t.values)]
    if not tracks:
        return False
    x = list(range(len(result.sessions)))
    fig, axs = plt.subplots(len(tracks), 1, figsize=(8, 1.9 * len(tracks) + 0.8), sharex=True, squeeze=False)
    for ax, tr in zip(axs[:, 0], tracks):
        ax.plot(x, tr.values, "o-", ms=3, lw=1, label=tr.target)
        if math.isfinite(tr.mu):
            ax.axhline(tr.mu, color="0.4", lw=0.8, ls="--")
            ax.axhspan(tr.mu - 3 * tr.sigma, tr.mu + 3 * tr.sigma, color="0.85", zorder=0)
        bad = [i for i, a in enumerate(tr.alarm) if a]
        if bad:
            ax.plot(bad, [tr.values[i] for i in bad], "rx", ms=8, label="alarm")
        ax.set_ylabel(f"{tr.target}\n[{unit}]", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    axs[0, 0].set_title(f"{title}\nbaseline (dashed) +- 3 sigma (grey), CUSUM alarms (x)", fontsize=9)
    axs[-1, 0].set_xlabel("session (time order)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return True


def write_report(result: SeriesResult, out_dir: str | Path, skipped: list[str] = (),
                 rules_path: str = "") -> Path:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    images = [name for name, (metric, title, unit) in PLOTS.items()
              if _plot(result, metric, title, unit, out / name)]
    ss = result.sessions
    md = ["# bsc analyze report", "",
          f"{len(ss)} session(s) in time order, {ss[0].name} to {ss[-1].name}."
          + (f" Rules: `{rules_path}`." if rules_path else ""), ""]
    md += ["## Alerts", ""]
    if not result.findings:
        md.append("None: every tracked quantity stayed within its baseline.")
    else:
        md += ["| session | state | severity | kind | target | rule | message |", "|---|---|---|---|---|---|---|"]
        for f in result.findings:
            md.append(f"| {f.session} | {f.state} | {f.severity} | {f.kind} | {f.target} | {f.rule} | {f.message} |")
    md += ["", "## Detectors", "",
           "| rule | metric | kind | direction | sigma floor | k | h |", "|---|---|---|---|---|---|---|"]
    for det in {t.detector.name: t.detector for t in result.tracks}.values():
        md.append(f"| {det.name} | {det.metric} | {det.kind} | {det.direction} | max({det.floor_abs:g}, "
                  f"{det.floor_rel:g} x baseline) | {det.k_ref:g} | {det.h:g} |")
    md += ["", "## Trends", ""]
    md += [f"![{name}]({name})" for name in images]
    md += ["", "## Per session", "", "```", summary_text(result, skipped), "```", ""]
    path = out / "report.md"
    path.write_text("\n".join(md))
    return path
