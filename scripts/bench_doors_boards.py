"""Doors and boards benchmark (issue 26): the association next to walls on the walks built for it.

Simulates each walk once (cached in ``--cache``): the ``small_room`` (door 1.5 cm recessed, board
2 cm proud; seeds 1 and 2), ``small_room_thin`` (both 1 cm), ``long_wall_boards`` (three doors and
three boards at 1, 1.5 and 2 cm on a 16 m room's long walls) and the ``demo`` walk (seeds 1 and 2),
3 mm range noise, no IMU, standing start. Runs SLAM on each with every configuration of
``--configs`` (``default``: ``configs/slam/default.yaml``'s defaults; else a YAML file, or
``name=FILE``), without the cloud (the recording on, so that the cloud pass places the segments for
the planes' outlines from the final map), evaluates against the ground truth and prints
one markdown table: associated segments on the right true plane (strict, and with coplanar pieces
as one surface), wall<->door/board confusions over the door and board segments, the door and
board segments on their own plane, ATE start-/SE(3)-aligned, the largest start-aligned position
error, the worst door/board extent error and excess (how much longer or taller than its face), the
health verdict, wall time. The goals of issue 26 are marked. A bar plot of the confusions and the ATE per walk and configuration goes to ``--plot``.

Usage:
    .venv/bin/python scripts/bench_doors_boards.py [--configs default,after=FILE] [--walks room,demo,...]
        [--cache /tmp/bench_doors_cache] [--out DIR] [--markdown FILE] [--plot FILE]
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from slam.config import SlamConfig

# name -> (world, duration s, seed)
WALKS: dict[str, tuple[str, float, int]] = {
    "room": ("small_room", 40.0, 1),
    "room_s2": ("small_room", 40.0, 2),
    "room_thin": ("small_room_thin", 40.0, 1),
    "long_wall": ("long_wall_boards", 60.0, 1),
    "demo": ("demo", 60.0, 1),
    "demo_s2": ("demo", 60.0, 2),
}
GOAL_RIGHT, GOAL_CONFUSION, GOAL_ATE_SE3, GOAL_MAX_ERR, GOAL_EXTENT = 0.99, 0.005, 0.002, 0.005, 0.10


@dataclass(frozen=True)
class Row:
    walk: str
    config: str
    strict: float
    surface: float
    confusion: float
    confusion_pure: float  # among single-surface segments (purity >= 0.9)
    n_child: int
    child_right: float
    ate_start: float
    ate_se3: float
    max_err: float
    extent_max: float
    excess_max: float  # how much longer or taller than its face the worst door or board plane is
    verdict: str
    wall_s: float


def _walk(name: str, cache: Path) -> tuple[Path, Path]:
    """The walk's bag and ground truth, simulated once."""
    from simulation.run import simulate

    world, duration, seed = WALKS[name]
    folder = cache / f"{world}_{duration:.0f}s_seed{seed}"
    done = folder / "done.json"
    if not done.is_file():
        folder.mkdir(parents=True, exist_ok=True)
        print(f"simulating {name} ({world}, {duration:.0f} s, seed {seed}) ...", flush=True)
        sim = simulate(world, "itc_backpack", duration=duration, seed=seed, out=folder / "walk.bag", progress=False)
        done.write_text(json.dumps({"bag": str(sim.bag), "gt": str(sim.gt)}))
    d = json.loads(done.read_text())
    return Path(d["bag"]), Path(d["gt"])


def _config(spec: str) -> tuple[str, SlamConfig]:
    """``default``, ``FILE`` or ``name=FILE`` -> (label, SlamConfig) without the cloud; the recording
    stays on (its pass over the scans places the segments for the final map's outlines)."""
    from slam.config import SlamConfig, load_slam_config

    label, _, path = spec.partition("=") if "=" in spec else (Path(spec).stem, "", spec)
    cfg = SlamConfig() if path == "default" else load_slam_config(path)
    return label, cfg.model_copy(update={"output": cfg.output.model_copy(update={"cloud": False, "rerun": True})})


def run_one(walk: str, label: str, cfg: SlamConfig, cache: Path, out: Path) -> Row:
    """SLAM on one walk with one configuration, evaluated."""
    from common.rig import resolve_rig
    from slam.evaluate import evaluate
    from slam.run import run_slam

    bag, gt = _walk(walk, cache)
    folder = out / f"{walk}__{label}"
    t0 = time.perf_counter()
    summary = run_slam(bag, resolve_rig("itc_backpack"), cfg, folder, progress=False)
    wall = time.perf_counter() - t0
    res = evaluate(folder, gt, map_alignment="se3")
    a = res.association
    assert a is not None and res.planes is not None
    ate = res.trajectory.ate
    child = [a.by_kind.get(k, (0, 0)) for k in ("door", "board")]
    n_child = sum(n for n, _ in child)
    extents = [m.extent_error_m for m in res.planes.matches if m.extent_error_m == m.extent_error_m]
    excess = [m.extent_excess_m for m in res.planes.matches if m.extent_excess_m == m.extent_excess_m]
    verdict = str((summary.get("health") or {}).get("verdict", "?"))
    return Row(walk, label, a.fraction_correct_of_associated, a.fraction_correct_surface_of_associated,
               a.confusion_fraction, a.confusion_fraction_pure, n_child, sum(c for _, c in child) / max(n_child, 1),
               ate["start_aligned"].rmse, ate["se3_aligned"].rmse, ate["start_aligned"].max,
               max(extents) if extents else float("nan"), max(excess) if excess else float("nan"), verdict, wall)


def table(rows: list[Row]) -> str:
    """The markdown table, goals marked in bold where met."""
    def b(text: str, ok: bool) -> str:
        return f"**{text}**" if ok else text

    out = ["| walk | config | right plane strict / surface | confusions (of door+board segs) | single-surface segs "
           "| door+board on own plane | ATE start / SE(3) | largest error | worst extent error / excess | verdict | wall |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(
            f"| {r.walk} | {r.config} | {100 * r.strict:.2f} / {b(f'{100 * r.surface:.2f} %', r.surface >= GOAL_RIGHT)} "
            f"| {b(f'{100 * r.confusion:.2f} %', r.confusion < GOAL_CONFUSION)} ({r.n_child}) "
            f"| {100 * r.confusion_pure:.2f} % | {100 * r.child_right:.1f} % "
            f"| {1e3 * r.ate_start:.2f} / {b(f'{1e3 * r.ate_se3:.2f} mm', r.ate_se3 < GOAL_ATE_SE3)} "
            f"| {b(f'{1e3 * r.max_err:.1f} mm', r.max_err < GOAL_MAX_ERR)} "
            f"| {b(f'{r.extent_max:.2f}', r.extent_max < GOAL_EXTENT)} / {b(f'{r.excess_max:.2f} m', r.excess_max < GOAL_EXTENT)} "
            f"| {r.verdict} | {r.wall_s:.0f} s |")
    return "\n".join(out)


def plot(rows: list[Row], path: Path) -> None:
    """Confusions and ATE per walk, one bar per configuration."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from common.atomic import atomic_path

    walks = list(dict.fromkeys(r.walk for r in rows))
    configs = list(dict.fromkeys(r.config for r in rows))
    by = {(r.walk, r.config): r for r in rows}
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    width = 0.8 / max(len(configs), 1)
    x = np.arange(len(walks))
    for i, c in enumerate(configs):
        conf = [100 * by[(w, c)].confusion if (w, c) in by else np.nan for w in walks]
        ate = [1e3 * by[(w, c)].ate_start if (w, c) in by else np.nan for w in walks]
        axes[0].bar(x + i * width, conf, width, label=c)
        axes[1].bar(x + i * width, ate, width, label=c)
    axes[0].axhline(100 * GOAL_CONFUSION, color="k", lw=0.8, ls="--", label="goal 0.5 %")
    axes[0].set_ylabel("wall <-> door/board confusions (% of door+board segments)")
    axes[1].set_yscale("log")
    top = max((1e3 * r.ate_start for r in rows), default=1.0)
    axes[1].set_ylim(0.1, max(10.0, 2.0 * top))  # from 0.1 mm, so that the bars compare
    axes[1].set_ylabel("ATE RMSE, start-aligned (mm, log)")
    for ax in axes:
        ax.set_xticks(x + 0.4 - width / 2, walks, rotation=20)
        ax.grid(axis="y", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("Doors and boards next to their walls (issue 26)")
    fig.tight_layout()
    with atomic_path(path, make_parents=True) as tmp:
        fig.savefig(tmp, format=path.suffix.lstrip(".") or "png", dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", default="default", help="comma-separated: default, FILE or name=FILE")
    ap.add_argument("--walks", default=",".join(WALKS), help=f"comma-separated of {', '.join(WALKS)}")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/bench_doors_cache"))
    ap.add_argument("--out", type=Path, default=None, help="run folders (default: <cache>/runs)")
    ap.add_argument("--markdown", type=Path, default=None)
    ap.add_argument("--plot", type=Path, default=None)
    args = ap.parse_args()
    walks = [w for w in args.walks.split(",") if w]
    unknown = [w for w in walks if w not in WALKS]
    if unknown:
        ap.error(f"--walks: unknown {', '.join(unknown)} (one of {', '.join(WALKS)})")
    configs = [_config(s) for s in args.configs.split(",") if s]
    out = args.out or args.cache / "runs"
    rows = []
    for w in walks:
        for label, cfg in configs:
            print(f"{w} / {label} ...", flush=True)
            rows.append(run_one(w, label, cfg, args.cache, out))
    text = table(rows)
    print(text)
    if args.markdown:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text(text + "\n")
    if args.plot:
        plot(rows, args.plot)


if __name__ == "__main__":
    main()
