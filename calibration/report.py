"""The calibration report folder: residuals before/after per scanner, parameter plots, summary.

``report.md`` (markdown summary: estimates, sigmas, changes, unobservable parameters, residuals,
rounds), ``residuals_<scanner>.png`` (histograms of the point-to-plane residuals before and
after), ``parameters_<scanner>.png`` (change of each parameter from the initial rig with 3-sigma
bars) and ``calibration.json`` (the same numbers). Written into a temporary folder that
replaces ``out_dir`` when complete.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from calibration.calibrate import Calibration
from calibration.observability import PARAMETERS
from common.atomic import atomic_dir
from common.rotations import matrix_to_rpy


def _stats(r: np.ndarray) -> dict[str, float]:
    if r.size == 0:
        return {"n": 0, "rms_mm": float("nan"), "median_abs_mm": float("nan")}
    return {"n": int(r.size), "rms_mm": float(np.sqrt(np.mean(r**2)) * 1e3),
            "median_abs_mm": float(np.median(np.abs(r)) * 1e3)}


def _params(T: np.ndarray) -> np.ndarray:
    return np.array([*matrix_to_rpy(T[:3, :3]), *T[:3, 3]])


def summary_dict(cal: Calibration) -> dict[str, Any]:
    """The report's numbers: per scanner estimates (rad, m), sigmas, changes and residuals."""
    sig = {p.scanner: p for p in cal.sigmas}
    out: dict[str, Any] = {"scanners": [], "warnings": cal.warnings, "converged": cal.converged,
                           "rounds": [r.__dict__ for r in cal.rounds],
                           "batch": {"iterations": cal.batch.iterations, "blocks": cal.batch.n_blocks,
                                     "seconds": cal.batch.seconds,
                                     "initial_error": cal.batch.initial_error,
                                     "final_error": cal.batch.final_error}}
    for s in cal.batch.scanners:
        p0 = _params(cal.initial_rig.scanner(s.name).T_body_scanner.matrix())
        p1 = _params(s.T_body_scanner)
        d = p1 - p0
        d[:3] = (d[:3] + np.pi) % (2 * np.pi) - np.pi
        rec: dict[str, Any] = {"name": s.name, "reference": s.reference, "points": s.n_points,
                               "parameters": dict(zip(PARAMETERS, p1.tolist(), strict=True)),
                               "change": dict(zip(PARAMETERS, d.tolist(), strict=True)),
                               "residuals_before": _stats(s.residuals_before),
                               "residuals_after": _stats(s.residuals_after)}
        if s.name in sig:
            rec["sigmas"] = dict(zip(PARAMETERS, sig[s.name].sigmas.tolist(), strict=True))
            rec["sigma_over_prior"] = dict(zip(PARAMETERS, sig[s.name].ratio.tolist(), strict=True))
            rec["unobservable"] = list(sig[s.name].unobservable)
        if s.time_offset_sigma is not None:
            rec["time_offset"] = cal.rig.scanner(s.name).time_offset
            rec["time_offset_sigma"] = s.time_offset_sigma
        out["scanners"].append(rec)
    return out


def _markdown(d: dict[str, Any]) -> str:
    lines = ["# Calibration report", ""]
    lines.append(f"Converged: {'yes' if d['converged'] else 'no'} after {len(d['rounds'])} round(s); "
                 f"last batch {d['batch']['iterations']} LM iterations over {d['batch']['blocks']} "
                 f"blocks in {d['batch']['seconds']:.1f} s.")
    lines += ["", "## Extrinsics (change from the initial rig, 1-sigma)", "",
              "| scanner | " + " | ".join(PARAMETERS) + " |", "|---" * 7 + "|"]
    for s in d["scanners"]:
        if s["reference"]:
            lines.append(f"| {s['name']} (reference) | " + " | ".join(["fixed"] * 6) + " |")
            continue
        cells = []
        for k, name in enumerate(PARAMETERS):
            f, unit = (np.degrees(1.0), "deg") if k < 3 else (1e3, "mm")
            c = f"{s['change'][name] * f:+.4f} ± {s['sigmas'][name] * f:.4f} {unit}"
            if name in s.get("unobservable", []):
                c += " **unobservable**"
            cells.append(c)
        lines.append(f"| {s['name']} | " + " | ".join(cells) + " |")
    for s in d["scanners"]:
        if "time_offset" in s:
            lines.append(f"\nTime offset {s['name']}: {s['time_offset'] * 1e3:+.3f} ± "
                         f"{s['time_offset_sigma'] * 1e3:.3f} ms")
    lines += ["", "## Point-to-plane residuals", "", "| scanner | points | RMS before (mm) | RMS after (mm) | "
              "median abs before | median abs after |", "|---|---|---|---|---|---|"]
    for s in d["scanners"]:
        b, a = s["residuals_before"], s["residuals_after"]
        lines.append(f"| {s['name']} | {a['n']} | {b['rms_mm']:.3f} | {a['rms_mm']:.3f} | "
                     f"{b['median_abs_mm']:.3f} | {a['median_abs_mm']:.3f} |")
    lines += ["", "## Warnings", ""]
    lines += [f"- {w}" for w in d["warnings"]] or ["- none: every parameter is constrained by the data"]
    lines += ["", "## Rounds (SLAM + batch)", "", "| round | planes | segments associated | points | "
              "change (deg) | change (mm) |", "|---|---|---|---|---|---|"]
    for r in d["rounds"]:
        lines.append(f"| {r['round']} | {r['planes']} | {r['segments_associated']} | {r['points']} | "
                     f"{np.degrees(r['change_rot']):.4f} | {r['change_trans'] * 1e3:.3f} |")
    return "\n".join(lines) + "\n"


def _plots(cal: Calibration, out: Path, d: dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for s in cal.batch.scanners:
        fig, ax = plt.subplots(figsize=(6, 4))
        both = np.concatenate([s.residuals_before, s.residuals_after]) * 1e3
        lim = float(np.percentile(np.abs(both), 99)) if both.size else 1.0
        bins = np.linspace(-lim, lim, 81).tolist()
        ax.hist(s.residuals_before * 1e3, bins=bins, alpha=0.5, label="before")
        ax.hist(s.residuals_after * 1e3, bins=bins, alpha=0.5, label="after")
        ax.set_xlabel("point-to-plane residual (mm)")
        ax.set_ylabel("virtual points")
        ax.set_title(f"{s.name}: residuals before / after calibration")
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / f"residuals_{s.name}.png", dpi=110)
        plt.close(fig)
    for rec in d["scanners"]:
        if rec["reference"]:
            continue
        fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
        for ax, ks, f, unit in ((axes[0], range(3), np.degrees(1.0), "deg"), (axes[1], range(3, 6), 1e3, "mm")):
            names = [PARAMETERS[k] for k in ks]
            val = np.array([rec["change"][n] for n in names]) * f
            err = 3 * np.array([rec["sigmas"][n] for n in names]) * f
            colors = ["tab:red" if n in rec["unobservable"] else "tab:blue" for n in names]
            ax.bar(names, val, yerr=err, capsize=6, color=colors)
            ax.axhline(0.0, color="k", lw=0.8)
            ax.set_ylabel(f"change from initial rig ({unit})")
        fig.suptitle(f"{rec['name']}: estimate - initial, 3-sigma bars (red: unobservable)")
        fig.tight_layout()
        fig.savefig(out / f"parameters_{rec['name']}.png", dpi=110)
        plt.close(fig)


def write_report(cal: Calibration, out_dir: str | Path) -> Path:
    """Write the report folder (see the module docstring); returns its path."""
    out = Path(out_dir)
    with atomic_dir(out) as tmp:
        d = summary_dict(cal)
        (tmp / "calibration.json").write_text(json.dumps(d, indent=2, default=float))
        (tmp / "report.md").write_text(_markdown(d))
        _plots(cal, tmp, d)
    return out
