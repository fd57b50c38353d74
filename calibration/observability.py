"""Observability of the extrinsic parameters: posterior standard deviations against the prior.

The covariance of ``E(s)`` (the cluster-robust one by default, see
:func:`calibration.calibrate.reported_covariance`, else the marginal one) is over gtsam's right-perturbation tangent of
``T_body_scanner`` (rotation, then translation, both in the scanner frame). The rig file's
parameters are roll, pitch, yaw (``R = Rz Ry Rx``) and the body-frame translation x, y, z, so
both the posterior and the prior covariance are mapped to those six by the Jacobian of
(rpy, t) wrt the tangent: ``d t / d v = R`` and ``d rpy / d omega`` (numerical, exact to ~1e-9).
A parameter whose posterior sigma is more than ``threshold`` times its prior sigma was not
constrained by the data (e.g. the translation along a straight corridor walked without turning).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from common.rotations import matrix_to_rpy
from slam.trajectory.interpolation import so3_exp

FloatArray = NDArray[np.float64]
PARAMETERS = ("roll", "pitch", "yaw", "x", "y", "z")


class UnobservableWarning(UserWarning):
    """A calibration parameter that the recording did not constrain."""


@dataclass(frozen=True)
class ParameterSigmas:
    """Per scanner: sigmas (6,) of (roll, pitch, yaw [rad], x, y, z [m]), the prior's sigmas in
    the same parameters, their ratio and the names of the unconstrained parameters."""

    scanner: str
    sigmas: FloatArray
    prior_sigmas: FloatArray
    ratio: FloatArray
    unobservable: tuple[str, ...]


def rpy_xyz_jacobian(T_body_scanner: FloatArray, eps: float = 1e-7) -> FloatArray:
    """(6, 6) Jacobian of (roll, pitch, yaw, x, y, z) wrt the right tangent (omega, v) of the pose."""
    R = np.asarray(T_body_scanner, dtype=float)[:3, :3]
    J = np.zeros((6, 6))
    for k in range(3):
        w = np.zeros(3)
        w[k] = eps
        a = np.array(matrix_to_rpy(R @ so3_exp(w)))
        b = np.array(matrix_to_rpy(R @ so3_exp(-w)))
        d = (a - b + np.pi) % (2 * np.pi) - np.pi
        J[:3, k] = d / (2 * eps)
    J[3:, 3:] = R
    return J


def parameter_covariance(T_body_scanner: FloatArray, tangent_covariance: FloatArray) -> FloatArray:
    """Covariance (6, 6) over (roll, pitch, yaw, x, y, z) from the tangent covariance."""
    J = rpy_xyz_jacobian(T_body_scanner)
    return J @ np.asarray(tangent_covariance, dtype=float) @ J.T


def parameter_sigmas(scanner: str, T_body_scanner: FloatArray, tangent_covariance: FloatArray,
                     prior_tangent_sigmas: FloatArray, threshold: float = 0.5) -> ParameterSigmas:
    """Sigmas of the six rig parameters and the ones whose sigma exceeds ``threshold`` x prior."""
    post = parameter_covariance(T_body_scanner, tangent_covariance)
    prior = parameter_covariance(T_body_scanner, np.diag(np.asarray(prior_tangent_sigmas, dtype=float) ** 2))
    s = np.sqrt(np.maximum(np.diag(post), 0.0))
    s0 = np.sqrt(np.diag(prior))
    ratio = s / s0
    bad = tuple(PARAMETERS[k] for k in range(6) if ratio[k] > threshold)
    return ParameterSigmas(scanner, s, s0, ratio, bad)


def warn_unobservable(p: ParameterSigmas) -> list[str]:
    """Emit an :class:`UnobservableWarning` per unconstrained parameter; returns the messages."""
    msgs = []
    for name in p.unobservable:
        k = PARAMETERS.index(name)
        unit, f = ("deg", np.degrees(1.0)) if k < 3 else ("mm", 1e3)
        msg = (f"scanner '{p.scanner}': parameter {name} is not constrained by the recording "
               f"(sigma {p.sigmas[k] * f:.3g} {unit} = {p.ratio[k]:.2f} x prior sigma "
               f"{p.prior_sigmas[k] * f:.3g} {unit})")
        warnings.warn(msg, UnobservableWarning, stacklevel=2)
        msgs.append(msg)
    return msgs
