"""Synthetic box room seen by three 2D scanners on a walking body, generated analytically.

Used by tests/test_backend.py and scripts/bench_backend.py. The true continuous trajectory is
the SE(3) interpolation of the true knots (what the back end models), so noise-free points fit
the model exactly. Rays from the true scanner pose at each beam time hit the nearest wall.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slam.backend import Backend, BackendConfig
from slam.trajectory.interpolation import interpolate_trajectory, knot_fractions, se3_exp

FloatArray = NDArray[np.float64]

# interior normals; n . x + d = 0 and n . x + d > 0 inside the room (8 x 6 x 3 m)
BOX_PLANES = np.array([
    [0.0, 0.0, 1.0, 1.3],    # 0 floor  z = -1.3
    [0.0, 0.0, -1.0, 1.7],   # 1 ceiling z = 1.7
    [1.0, 0.0, 0.0, 4.0],    # 2 wall x = -4
    [-1.0, 0.0, 0.0, 4.0],   # 3 wall x = 4
    [0.0, 1.0, 0.0, 3.0],    # 4 wall y = -3
    [0.0, -1.0, 0.0, 3.0],   # 5 wall y = 3
])


def _pose(rotvec: FloatArray, t: FloatArray) -> FloatArray:
    T = se3_exp(np.concatenate([rotvec, np.zeros(3)]))
    T[:3, 3] = t
    return T


SCANNERS = [  # T_body_scanner: horizontal reference, two tilted at the back
    np.eye(4),
    _pose(np.array([0.9, 0.35, 0.5]), np.array([-0.25, 0.15, -0.1])),
    _pose(np.array([-0.9, 0.35, -0.5]), np.array([-0.25, -0.15, -0.1])),
]


def walking_knots(duration: float = 2.0, rate: float = 40.0,
                  speed: float = 1.2) -> tuple[FloatArray, FloatArray]:
    """Knot times (K,) and true ``T_world_body`` (K, 4, 4) of a walk with bounce, sway and a turn."""
    t = np.arange(round(duration * rate) + 1) / rate
    x = -2.5 + speed * t
    y = -1.0 + 0.4 * np.sin(0.9 * t)
    z = 0.02 * np.sin(2 * np.pi * 2.0 * t)
    yaw = 0.25 * t + 0.04 * np.sin(2 * np.pi * 1.0 * t)
    roll = 0.02 * np.sin(2 * np.pi * 1.0 * t)
    pitch = 0.015 * np.sin(2 * np.pi * 2.0 * t)
    poses = np.array([
        _pose(np.array([r, p, w]), np.array([a, b, c]))
        for r, p, w, a, b, c in zip(roll, pitch, yaw, x, y, z, strict=True)
    ])
    return t, poses


@dataclass
class Scene:
    """Points of all scans grouped into observation blocks (interval, plane)."""

    knot_times: FloatArray
    knot_poses: FloatArray
    planes: FloatArray                      # (6, 4) true (n, d)
    blocks: list[dict]                      # knot, plane, points_body, points_scanner, scanner, alphas, sigmas, outlier
    n_points: int


def make_scene(duration: float = 2.0, beams: int = 91, sigma_range: float = 0.0,
               outlier_fraction: float = 0.0, seed: int = 0,
               scan_offsets: tuple[float, ...] = (0.0, 0.008, 0.016)) -> Scene:
    """Scans at 40 Hz of each scanner (270 deg, ``beams`` beams over 18.75 ms, first beam at the
    knot time + offset), ranges with Gaussian noise ``sigma_range`` along the ray; a fraction of
    points are displaced 5-30 cm towards the scanner (objects in front of a wall: wrong
    associations). Sigmas are ``sigma_range |n . ray|`` (at least 1 mm)."""
    rng = np.random.default_rng(seed)
    kt, kp = walking_knots(duration)
    angles = np.deg2rad(np.linspace(-135.0, 135.0, beams))
    dt_beam = 0.01875 / (beams - 1)
    blocks: dict[tuple[int, int, int], dict[str, list]] = {}
    n_total = 0
    for s, T_bs in enumerate(SCANNERS):
        for i in range(kt.size - 1):
            times = kt[i] + scan_offsets[s] + np.arange(beams) * dt_beam
            ok_t = times <= kt[-1]
            times, ang = times[ok_t], angles[ok_t]
            T_wb = interpolate_trajectory(kt, kp, times)
            T_ws = T_wb @ T_bs
            u_s = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], axis=1)
            o = T_ws[:, :3, 3]
            u = np.einsum("nij,nj->ni", T_ws[:, :3, :3], u_s)
            nu = u @ BOX_PLANES[:, :3].T                       # (n, 6)
            no = o @ BOX_PLANES[:, :3].T + BOX_PLANES[:, 3]
            lam = np.where(nu < -1e-9, -no / np.where(nu < -1e-9, nu, -1.0), np.inf)
            j = np.argmin(lam, axis=1)
            r = lam[np.arange(j.size), j]
            cos_inc = np.abs(nu[np.arange(j.size), j])
            valid = np.isfinite(r) & (r > 0.1) & (r < 30.0) & (cos_inc > 0.15)
            r_meas = r + sigma_range * rng.standard_normal(r.size)
            outl = rng.random(r.size) < outlier_fraction
            r_meas = np.where(outl, r_meas - rng.uniform(0.05, 0.3, r.size), r_meas)
            p_s = u_s * r_meas[:, None]
            p_b = p_s @ T_bs[:3, :3].T + T_bs[:3, 3]
            idx, alpha = knot_fractions(kt, times)
            sig = np.maximum(sigma_range * cos_inc, 1e-3)
            for k in np.flatnonzero(valid):
                key = (int(idx[k]), int(j[k]), s)
                b = blocks.setdefault(key, {"pb": [], "ps": [], "al": [], "sg": [], "out": []})
                b["pb"].append(p_b[k])
                b["ps"].append(p_s[k])
                b["al"].append(alpha[k])
                b["sg"].append(sig[k])
                b["out"].append(outl[k])
                n_total += 1
    out = []
    for (i, j, s), b in sorted(blocks.items()):
        out.append({
            "knot": i, "plane": j, "scanner": s,
            "points_body": np.array(b["pb"]), "points_scanner": np.array(b["ps"]),
            "alphas": np.array(b["al"]), "sigmas": np.array(b["sg"]),
            "outlier": np.array(b["out"], dtype=bool),
        })
    return Scene(kt, kp, BOX_PLANES.copy(), out, n_total)


def perturb_pose(T: FloatArray, rng: np.random.Generator, sigma_t: float, sigma_r: float) -> FloatArray:
    """``T Exp(delta)`` with Gaussian rotation [rad] and translation [m] perturbations."""
    d = np.concatenate([rng.normal(0, sigma_r, 3), rng.normal(0, sigma_t, 3)])
    return T @ se3_exp(d)


def perturbed_backend(scene: Scene, config: BackendConfig, seed: int = 3) -> Backend:
    """A back end holding ``scene``'s observations, its poses (all but the first) perturbed by
    1 cm / 0.3 deg and its planes by 0.01 (normal) / 2 cm (offset); the first two planes horizontal."""
    rng = np.random.default_rng(seed)
    be = Backend(config)
    for i, (t, T) in enumerate(zip(scene.knot_times, scene.knot_poses, strict=True)):
        be.add_pose(t, T if i == 0 else perturb_pose(T, rng, 0.01, 0.3 * np.pi / 180.0))
    for j, (n0, d0) in enumerate(zip(scene.planes[:, :3], scene.planes[:, 3], strict=True)):
        be.add_plane(j, n0 + rng.normal(0.0, 0.01, 3), d0 + rng.normal(0.0, 0.02), horizontal=j < 2)
    for b in scene.blocks:
        be.add_observations(b["knot"], b["plane"], b["points_body"], b["alphas"], b["sigmas"])
    return be
