"""A scanner's noise model estimated from its own scans: range noise, its growth with range,
range quantisation and angular step.

``estimate(scanlines) -> NoiseModel`` looks at one scanner's scanlines (scanner
frame, scan order) and needs no ground truth:

* **Range noise** from triples of valid beams ``i - k, i, i + k``. The inverse
  range of a straight line is ``u(theta) = A cos(theta) + B sin(theta)``, so
  any three beams on one line satisfy exactly
  ``u0 sin(t2 - t1) + u2 sin(t1 - t0) - u1 sin(t2 - t0) = 0``, whatever the
  wall's distance, incidence or the angular step. With range noise the left
  side has, to first order, the variance
  ``sigma^2 (sin^2(t2 - t1) / r0^4 + sin^2(t1 - t0) / r2^4 + sin^2(t2 - t0) / r1^4)``;
  dividing by its square root gives one sample ``z`` of the range noise per
  triple. (Plain second differences of the ranges also carry the wall's
  curvature in polar coordinates, ``r (1 + sin^2 a) / cos^2 a dtheta^2`` at
  incidence ``a``: about 1 cm at 5 m and 60 deg with 1 deg steps.)
* **Lag.** Real scanners' range errors are correlated along the scan: on a
  straight wall of the obstacle-detector bag (Hokuyo URG class) neighbouring
  beams' errors correlate at 0.9, the beam-to-beam noise is 3-4 mm but the
  points scatter about 9 mm about the wall's line. A segment's line sees the
  error at its own scale, so the model's noise comes from triples ``LAG``
  beams apart (a 9-beam stretch, the size of the shortest segments the noise-
  derived defaults keep), while consecutive triples (``k = 1``) give the
  beam-to-beam noise ``beam_sigma``, reported alongside. For white noise both
  agree (within a few per cent).
* **Robust to corners, edges, mixed pixels and clutter:** a consecutive triple
  is *clean* when its range steps stay within ``JUMP_STEPS`` beam spacings
  plus ``JUMP_SIGMAS`` noise (no depth jump) and its ``|z|`` within
  ``TRIM_SIGMAS`` beam-to-beam scales; a lagged triple is used only when every
  consecutive triple inside its stretch is clean. The samples then go into a
  robust scale: a start from the 25 % quantile of ``|z|`` (at least the
  quantisation's ``q / sqrt(12)``), then rounds of the root mean square of the
  samples within ``TRIM_SIGMAS`` of the current scale, corrected for the
  Gaussian truncation; from below, the rounds climb to the inliers' scale and
  stop there. (Not the median absolute deviation: quantised ranges give
  nearly ternary ``z`` whose median says nothing about their spread.)
* **Growth with range:** the same scale in up to ``MAX_BINS`` range bins
  (quantiles of the middle beam's range, at least ``BIN_SAMPLES`` triples
  each, trimming started from the overall scale), fitted by weighted least
  squares as ``sigma(r) = sigma0 + slope * r``. The slope is kept only when it
  is positive and more than two standard errors from zero; otherwise the
  noise is constant.
* **Quantisation:** the lattice of the range values. Candidate steps are the
  smallest differences between distinct range values; a candidate ``q`` is the
  step when the ranges' phases ``2 pi r / q`` agree (mean resultant length over
  ``LATTICE_COHERENCE``), so a lattice with any offset is found, and float32
  round-off is tolerated.
* **Angular step:** the median angle between consecutive valid beams.

What the model reports: **the total effective range noise**, quantisation
included. A uniform quantisation error of step ``q`` adds ``q^2 / 12`` to the
variance, and a line fit sees both alike, so ``sigma(r)`` (``sigma0``,
``slope``) is what the segmenters' thresholds follow. Averaged over many
walls, quantisation with ``q`` well above the sensor noise still enters the
triples with variance ``q^2 / 12`` (a ramp's quantisation error is a sawtooth
whose second differences have that mean square over the ramp's slopes), so
the estimate of the total holds in that regime too. ``sensor_sigma(r) =
sqrt(sigma(r)^2 - q^2 / 12)`` is the sensor's own noise; it is a difference of
two estimates and only meaningful when it is not much smaller than ``q / 3``.

``SIGMA_FLOOR`` bounds the noise below (0.5 mm): noise-free or float32-only
inputs give a usable model rather than zero thresholds.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from segmentation.scanline import Scanline

FloatArray = NDArray[np.float64]

#: smallest noise (m) a model reports
SIGMA_FLOOR = 0.0005
#: triples whose range steps exceed this many beam spacings (r * dtheta) plus JUMP_SIGMAS noise are dropped
JUMP_STEPS = 10.0
JUMP_SIGMAS = 8.0
#: the robust scale keeps samples within this many scales; rounds of trimming
TRIM_SIGMAS = 3.5
TRIM_ROUNDS = 30
#: range bins for the growth with range: at most this many, each with at least BIN_SAMPLES triples
MAX_BINS = 8
BIN_SAMPLES = 300
#: beams between the triple's beams of the noise estimate (module docstring)
LAG = 4
#: fewest triples an estimate needs
MIN_SAMPLES = 30
#: mean resultant length of the range phases above which a lattice step is accepted
LATTICE_COHERENCE = 0.9
#: a candidate difference is tried as up to this many lattice steps
MAX_DIVISOR = 5
#: the noise and angular step every segmenter's fixed defaults assume (a UTM-30LX indoors)
REFERENCE_SIGMA = 0.003
REFERENCE_ANGLE_STEP = math.radians(0.25)


def _truncated_var_factor(c: float) -> float:
    """Variance of a standard normal truncated to [-c, c]."""
    phi = math.exp(-0.5 * c * c) / math.sqrt(2.0 * math.pi)
    mass = math.erf(c / math.sqrt(2.0))
    return 1.0 - 2.0 * c * phi / mass


_TRUNC = _truncated_var_factor(TRIM_SIGMAS)
_Q25 = 0.31863936396437514  # 25 % quantile of |N(0, 1)|


@dataclass(frozen=True)
class NoiseModel:
    """One scanner's noise: effective range noise ``sigma(r) = sigma0 + slope * r`` (m, quantisation
    included), range quantisation step ``quantum`` (m, 0 = none found) and ``angle_step`` (rad).

    ``range_ref`` is the median range of the samples (m), where ``sigma_ref`` is quoted;
    ``beam_sigma`` the beam-to-beam noise at ``range_ref`` (m, from consecutive triples; 0 = not
    estimated);
    ``n_samples`` and ``n_scans`` say how much data the estimate rests on (0 for a model
    stated by hand, see ``NoiseModel.of``).
    """

    sigma0: float
    slope: float
    quantum: float
    angle_step: float
    range_ref: float = 5.0
    beam_sigma: float = 0.0
    scanner_id: str = "scanner"
    n_samples: int = 0
    n_scans: int = 0

    def __post_init__(self) -> None:
        for name in ("sigma0", "angle_step", "range_ref"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"NoiseModel.{name}={v!r} is invalid: must be finite and > 0")
        for name in ("slope", "quantum", "beam_sigma"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"NoiseModel.{name}={v!r} is invalid: must be finite and >= 0")

    @classmethod
    def of(cls, sigma: float, angle_step: float, *, slope: float = 0.0, quantum: float = 0.0,
           scanner_id: str = "scanner") -> NoiseModel:
        """A model stated by hand: effective noise ``sigma + slope * r`` (m), step ``angle_step`` (rad)."""
        return cls(float(sigma), float(slope), float(quantum), float(angle_step), scanner_id=scanner_id)

    def sigma(self, r: float | FloatArray) -> float | FloatArray:
        """Effective range noise (m) at range ``r`` (m), quantisation included."""
        return self.sigma0 + self.slope * r

    @property
    def sigma_ref(self) -> float:
        """Effective range noise (m) at ``range_ref``."""
        return float(self.sigma(self.range_ref))

    def sensor_sigma(self, r: float) -> float:
        """The sensor's own range noise at ``r`` (m): the effective noise without the quantisation's share."""
        return math.sqrt(max(float(self.sigma(r)) ** 2 - self.quantum**2 / 12.0, 0.0))

    def __str__(self) -> str:
        mm = 1e3
        growth = f"{mm * self.sigma0:.1f} mm + {mm * self.slope:.2f} mm/m x r" if self.slope > 0 else "constant"
        quant = f"{mm * self.quantum:g} mm" if self.quantum > 0 else ("none found" if self.n_samples else "none")
        sensor = (f"; without quantisation {mm * self.sensor_sigma(self.range_ref):.1f} mm"
                  if self.quantum > 0 else "")
        beam = f"; beam to beam {mm * self.beam_sigma:.1f} mm" if self.beam_sigma > 0 else ""
        source = (f"from {self.n_scans} scans, {self.n_samples} triples" if self.n_samples
                  else "stated, not estimated")
        return (f"noise model [{self.scanner_id}]: range noise {mm * self.sigma_ref:.1f} mm at "
                f"{self.range_ref:.1f} m ({growth}; quantisation included{sensor}{beam}), range quantisation "
                f"{quant}, angular step {math.degrees(self.angle_step):.4g} deg; {source}")


#: the scanner every segmenter's fixed defaults are stated for: 3 mm noise, 0.25 deg steps
REFERENCE = NoiseModel.of(REFERENCE_SIGMA, REFERENCE_ANGLE_STEP, scanner_id="UTM-30LX (reference)")


# ---- estimation ------------------------------------------------------------------------------


def estimate(scanlines: Scanline | Iterable[Scanline], lag: int | None = None) -> NoiseModel:
    """The noise model of one scanner from its scanlines (a ``Scanline`` or an iterable of them).

    ``lag``: beams between a triple's beams (default ``LAG``; 1 = consecutive
    beams only, the beam-to-beam noise). With fewer than ``MIN_SAMPLES`` clean
    stretches of ``2 lag + 1`` beams the consecutive triples are used.
    Raises ValueError when the scanlines come from several scanners (see
    ``estimate_per_scanner``) or hold fewer than ``MIN_SAMPLES`` triples of
    consecutive valid beams.
    """
    lines = [scanlines] if isinstance(scanlines, Scanline) else list(scanlines)
    if not lines:
        raise ValueError("noise estimate: no scanlines given")
    ids = sorted({ln.scanner_id for ln in lines})
    if len(ids) > 1:
        raise ValueError(f"noise estimate: scanlines of several scanners ({', '.join(ids)}); "
                         "use estimate_per_scanner")
    return _estimate(lines, ids[0], lag)


def estimate_per_scanner(scanlines: Iterable[Scanline], lag: int | None = None) -> dict[str, NoiseModel]:
    """One noise model per ``scanner_id`` among the scanlines."""
    groups: dict[str, list[Scanline]] = {}
    for ln in scanlines:
        groups.setdefault(ln.scanner_id, []).append(ln)
    if not groups:
        raise ValueError("noise estimate: no scanlines given")
    return {sid: _estimate(lines, sid, lag) for sid, lines in groups.items()}


def _estimate(lines: list[Scanline], scanner_id: str, lag: int | None) -> NoiseModel:
    lag = LAG if lag is None else lag
    if lag < 1:
        raise ValueError(f"noise estimate: lag={lag} is invalid: must be >= 1")
    step = angle_step(lines)
    fine = [triple_residuals(ln, 1, step) for ln in lines]
    z1 = np.concatenate([z for z, _ in fine])
    ok1 = np.isfinite(z1)
    if np.count_nonzero(ok1) < MIN_SAMPLES:
        raise ValueError(f"noise estimate for '{scanner_id}': only {np.count_nonzero(ok1)} triples of consecutive "
                         f"valid beams in {len(lines)} scanline(s), need {MIN_SAMPLES}")
    valid_r = np.concatenate([ln.ranges[ln.valid_index] for ln in lines])
    quantum = detect_quantum(valid_r)
    s1 = robust_scale(z1[ok1], quantum=quantum)
    z_fine, r_fine, z_lag, r_lag = [], [], [], []
    for ln, (z, jump) in zip(lines, fine, strict=True):
        r = ln.ranges
        with np.errstate(invalid="ignore"):
            clean = np.isfinite(z) & (jump <= (JUMP_STEPS * step) * r + JUMP_SIGMAS * s1)
        z_fine.append(z[clean])
        r_fine.append(r[clean])
        if lag == 1:
            continue
        with np.errstate(invalid="ignore"):
            clean &= np.abs(z) <= TRIM_SIGMAS * s1
        # lag triple at i: every consecutive triple centred in i - lag + 1 .. i + lag - 1 is clean
        zk, _ = triple_residuals(ln, lag, step)
        bad = np.concatenate(([0], np.cumsum(~clean)))
        i = np.arange(lag, r.shape[0] - lag)
        keep = (bad[i + lag] - bad[i - lag + 1] == 0) & np.isfinite(zk[i])
        z_lag.append(zk[i[keep]])
        r_lag.append(r[i[keep]])
    z, r_mid = np.concatenate(z_fine), np.concatenate(r_fine)
    fine_model = _fit_growth(z, r_mid, quantum) if z.size >= MIN_SAMPLES else None
    if lag > 1 and sum(a.size for a in z_lag) >= MIN_SAMPLES:
        z, r_mid = np.concatenate(z_lag), np.concatenate(r_lag)
    # else: too few clean stretches of 2 lag + 1 beams (one cluttered scan): the consecutive triples
    if z.size < MIN_SAMPLES:
        raise ValueError(f"noise estimate for '{scanner_id}': only {z.size} triples of consecutive valid beams "
                         f"without a depth jump in {len(lines)} scanline(s), need {MIN_SAMPLES}")
    sigma0, slope, r_ref = _fit_growth(z, r_mid, quantum)
    beam_sigma = fine_model[0] + fine_model[1] * r_ref if fine_model is not None else s1
    return NoiseModel(
        sigma0=sigma0,
        slope=slope,
        quantum=quantum,
        angle_step=step,
        range_ref=r_ref,
        beam_sigma=max(beam_sigma, SIGMA_FLOOR),
        scanner_id=scanner_id,
        n_samples=int(z.size),
        n_scans=len(lines),
    )


def triple_residuals(line: Scanline, lag: int, step: float) -> tuple[FloatArray, FloatArray]:
    """Range-noise samples of the beam triples ``i - lag, i, i + lag`` of a scanline, per beam ``i``.

    Returns ``z`` (m: the collinearity residual of the inverse ranges over its
    standard deviation per unit range noise; NaN where a beam is invalid, at
    the ends, or where the beams do not turn one way by about ``lag * step``)
    and the larger range step (m) between the triple's neighbouring beams
    (meaningful for ``lag = 1``).
    """
    n = line.n_beams
    z = np.full(n, np.nan)
    jump = np.full(n, np.nan)
    v = line.valid
    r_all = line.ranges
    a_all = line.angles
    i = np.arange(lag, n - lag)
    i = i[v[i - lag] & v[i] & v[i + lag]]
    if i.size == 0:
        return z, jump
    r0, r1, r2 = r_all[i - lag], r_all[i], r_all[i + lag]
    d10 = np.remainder(a_all[i] - a_all[i - lag] + np.pi, 2 * np.pi) - np.pi
    d21 = np.remainder(a_all[i + lag] - a_all[i] + np.pi, 2 * np.pi) - np.pi
    # beams in one turning sense, neither repeated nor far apart (an array of points may be anything)
    span = 3.0 * lag * step
    good = (d10 * d21 > 0) & (np.abs(d10) <= span) & (np.abs(d21) <= span)
    i, r0, r1, r2, d10, d21 = i[good], r0[good], r1[good], r2[good], d10[good], d21[good]
    s10, s21, s20 = np.sin(d10), np.sin(d21), np.sin(d10 + d21)
    e = s21 / r0 + s10 / r2 - s20 / r1
    sd = np.sqrt((s21 / r0**2) ** 2 + (s10 / r2**2) ** 2 + (s20 / r1**2) ** 2)
    z[i] = e / sd
    jump[i] = np.maximum(np.abs(r1 - r0), np.abs(r2 - r1))
    return z, jump


def robust_scale(z: FloatArray, start: float | None = None, quantum: float = 0.0) -> float:
    """Standard deviation of the inlying part of zero-mean samples ``z`` (see the module docstring).

    Rounds of the truncation-corrected root mean square of the samples within
    ``TRIM_SIGMAS`` scales, from ``start`` or from the 25 % quantile of ``|z|``
    but at least the quantisation's ``quantum / sqrt(12)`` (quantised ranges
    give many near-zero samples). Started low, the rounds climb to the
    inliers' scale and stop there: far outliers never enter, even when they
    are a third of the samples.
    """
    a = np.abs(z)
    if a.size == 0:
        return 0.0
    if start is None:
        s = max(float(np.quantile(a, 0.25)) / _Q25, quantum / math.sqrt(12.0))
    else:
        s = start
    if not s > 0:
        s = float(np.sqrt(np.mean(a * a)))
    for _ in range(TRIM_ROUNDS):
        kept = a[a <= TRIM_SIGMAS * s]
        if kept.size == 0 or not s > 0:
            break
        s_new = float(np.sqrt(np.mean(kept * kept) / _TRUNC))
        if abs(s_new - s) <= 1e-4 * s:
            return s_new
        s = s_new
    return s


def _fit_growth(z: FloatArray, r: FloatArray, quantum: float) -> tuple[float, float, float]:
    """(sigma0, slope, reference range) of ``sigma(r) = sigma0 + slope * r`` from samples ``z`` at ranges ``r``."""
    r_ref = float(np.median(r))
    total = max(robust_scale(z, quantum=quantum), SIGMA_FLOOR)
    n_bins = min(MAX_BINS, z.size // BIN_SAMPLES)
    if n_bins < 2:
        return total, 0.0, r_ref
    order = np.argsort(r, kind="stable")
    rb, sb, wb = [], [], []
    for part in np.array_split(order, n_bins):
        s = robust_scale(z[part], start=total)
        if s > 0:
            rb.append(float(np.median(r[part])))
            sb.append(s)
            wb.append(part.size / (s * s))  # the scale's variance is about s^2 / (2 n)
    if len(rb) < 2:
        return total, 0.0, r_ref
    x, y, w = np.asarray(rb), np.asarray(sb), np.asarray(wb)
    xm = float(np.sum(w * x) / np.sum(w))
    ym = float(np.sum(w * y) / np.sum(w))
    sxx = float(np.sum(w * (x - xm) ** 2))
    if sxx <= 0:
        return total, 0.0, r_ref
    slope = float(np.sum(w * (x - xm) * (y - ym)) / sxx)
    # the slope's standard error from the weights (each bin's scale has variance s^2 / (2 n))
    se = math.sqrt(0.5 / sxx)
    if not slope > 2.0 * se:
        return total, 0.0, r_ref
    sigma_at_ref = ym + slope * (r_ref - xm)
    sigma0 = sigma_at_ref - slope * r_ref
    if sigma0 < SIGMA_FLOOR:  # keep the fitted noise at the typical range, pin the intercept
        sigma0 = SIGMA_FLOOR
        slope = max((sigma_at_ref - SIGMA_FLOOR) / r_ref, 0.0)
    return sigma0, slope, r_ref


def detect_quantum(ranges: FloatArray) -> float:
    """The step (m) of the lattice the range values lie on, or 0 when they lie on none.

    Candidates are the smallest differences between distinct values (beyond
    float32 round-off) and their divisors up to ``MAX_DIVISOR``; the first
    whose phases ``2 pi r / q`` agree is the step.
    """
    r = np.asarray(ranges, dtype=np.float64)
    r = r[np.isfinite(r) & (r > 0)]
    if r.size < MIN_SAMPLES:
        return 0.0
    tol = 4.0 * float(np.max(r)) * 2.0**-23  # float32 round-off at the largest range
    u = np.unique(r)
    d = np.diff(u)
    d = np.sort(d[d > tol])
    if d.size == 0:
        return 0.0
    tried = 0
    looked = 0
    k = 0
    while k < d.size and tried < 5 and looked < 200:
        looked += 1
        # a cluster of nearly equal differences (float32 jitter) around its smallest member
        c_end = int(np.searchsorted(d, d[k] * 1.02 + tol, side="right"))
        support = c_end - k
        q_mean = float(np.mean(d[k:c_end]))
        k = c_end
        if support < max(3, d.size // 200):
            continue
        tried += 1
        # the difference may span several steps (few values, as in one scan): its largest divisor
        # that is a lattice step (GCD-like)
        for m in range(1, MAX_DIVISOR + 1):
            q = _lattice_step(r, q_mean / m)
            if q > 0:
                return q
    return 0.0


def _lattice_step(r: FloatArray, q_mean: float) -> float:
    """``q_mean`` (or it snapped to a round number) if the values lie on a lattice of that step, else 0.

    The mean of measured differences carries float32 jitter, which adds up over
    ``r / q`` steps: it is also tried snapped to 2 and 3 significant digits
    (steps are round numbers in practice).
    """
    best_q, best_c = 0.0, 0.0
    for q in (float(f"{q_mean:.2g}"), float(f"{q_mean:.3g}"), q_mean):
        c = float(abs(np.mean(np.exp(2j * np.pi * r / q))))
        if c > best_c + 1e-9:
            best_q, best_c = q, c
    return best_q if best_c >= LATTICE_COHERENCE else 0.0


def angle_step(lines: Iterable[Scanline]) -> float:
    """Median angle (rad) between consecutive valid beams of the scanlines."""
    steps = []
    for ln in lines:
        v = ln.valid
        both = v[1:] & v[:-1]
        d = np.abs(np.remainder(np.diff(ln.angles)[both] + np.pi, 2 * np.pi) - np.pi)
        steps.append(d[d > 0])
    s = np.concatenate(steps) if steps else np.empty(0)
    if s.size == 0:
        raise ValueError("noise estimate: no two consecutive valid beams to measure the angular step")
    return float(np.median(s))
