"""The scanner noise model (``segmentation.noise``) and the segmenters' noise-derived defaults."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

import segmentation as sg
from segmentation.noise import REFERENCE, NoiseModel, detect_quantum, estimate, estimate_per_scanner
from simulation.scanline import ScannerSpec, World2D, random_room, scan

DEG = math.pi / 180.0


def _line(s: object) -> sg.Scanline:
    return sg.Scanline.from_ranges(s.ranges, s.angles, s.times, range_min=s.range_min,  # type: ignore[attr-defined]
                                   range_max=s.range_max)  # type: ignore[attr-defined]


def _rooms(sigma: float, quantization: float | None = None, n: int = 6) -> list[sg.Scanline]:
    return [_line(random_room(seed, noise_sigma=sigma, quantization=quantization)) for seed in range(n)]


def _office() -> World2D:
    """An 8 x 5 m room with a pillar, a cabinet and an alcove: corners and occlusions."""
    return World2D.from_pieces([
        ("south", [(-4.0, -2.5), (4.0, -2.5)]),
        ("east", [(4.0, -2.5), (4.0, 2.5)]),
        ("north_a", [(4.0, 2.5), (0.5, 2.5)]),
        ("alcove_e", [(0.5, 2.5), (0.5, 2.9)]),
        ("alcove", [(0.5, 2.9), (-0.7, 2.9)]),
        ("alcove_w", [(-0.7, 2.9), (-0.7, 2.5)]),
        ("north_b", [(-0.7, 2.5), (-4.0, 2.5)]),
        ("west", [(-4.0, 2.5), (-4.0, -2.5)]),
        ("pillar_s", [(1.5, -0.3), (2.1, -0.3)]),
        ("pillar_e", [(2.1, -0.3), (2.1, 0.3)]),
        ("pillar_n", [(2.1, 0.3), (1.5, 0.3)]),
        ("pillar_w", [(1.5, 0.3), (1.5, -0.3)]),
        ("cabinet", [(-3.0, -2.5), (-3.0, -1.9)]),
        ("cabinet_front", [(-3.0, -1.9), (-2.0, -1.9)]),
        ("cabinet_side", [(-2.0, -1.9), (-2.0, -2.5)]),
    ])


def _office_scans(spec: ScannerSpec, n: int = 12) -> list[tuple[object, sg.Scanline]]:
    rng = np.random.default_rng(7)
    out = []
    for k in range(n):
        pose = (float(rng.uniform(-2.5, 0.5)), float(rng.uniform(-1.2, 1.2)), float(rng.uniform(-np.pi, np.pi)))
        s = scan(_office(), pose, spec, seed=k)
        out.append((s, _line(s)))
    return out


# ---- the estimate ------------------------------------------------------------------------------
@pytest.mark.parametrize("quantization", [None, 0.01])
@pytest.mark.parametrize("sigma", [0.001, 0.003, 0.01, 0.03])
def test_noise_within_20_percent(sigma: float, quantization: float | None) -> None:
    model = estimate(_rooms(sigma, quantization))
    q = quantization or 0.0
    effective = math.sqrt(sigma**2 + q**2 / 12.0)
    assert model.sigma_ref == pytest.approx(effective, rel=0.2)
    assert model.beam_sigma == pytest.approx(effective, rel=0.2)
    assert model.quantum == pytest.approx(q)
    assert model.angle_step == pytest.approx(0.25 * DEG)
    if sigma >= q / 3:  # the sensor's own share is identifiable
        assert model.sensor_sigma(model.range_ref) == pytest.approx(sigma, rel=0.2)


@pytest.mark.parametrize("quantization", [None, 0.01])
def test_range_growth_recovered(quantization: float | None) -> None:
    rng = np.random.default_rng(3)
    lines = []
    for seed in range(12):
        s = random_room(seed, noise_sigma=0.0, radius=(2.0, 12.0))
        true = np.where(np.isfinite(s.true_ranges), s.true_ranges, 0.0)
        r = s.true_ranges + rng.standard_normal(true.size) * (0.002 + 0.003 * true)
        if quantization:
            r = np.round(r / quantization) * quantization
        lines.append(sg.Scanline.from_ranges(r, s.angles, s.times, range_min=s.range_min, range_max=s.range_max))
    model = estimate(lines)
    assert model.slope == pytest.approx(0.003, rel=0.25)
    for r in (1.0, 3.0, 8.0):
        assert model.sensor_sigma(r) == pytest.approx(0.002 + 0.003 * r, rel=0.2)


def test_constant_noise_has_no_slope() -> None:
    assert estimate(_rooms(0.005, n=10)).slope == 0.0


@pytest.mark.parametrize(("step_deg", "n_beams"), [(1.0, 181), (0.5, 361), (0.25, 1081), (0.3516, 726)])
def test_angular_step_recovered(step_deg: float, n_beams: int) -> None:
    spec = ScannerSpec(n_beams=n_beams, angle_min=-0.5 * (n_beams - 1) * step_deg * DEG,
                       angle_increment=step_deg * DEG, noise_sigma=0.01)
    model = estimate([line for _, line in _office_scans(spec, 4)])
    assert model.angle_step == pytest.approx(step_deg * DEG, rel=1e-9)
    assert model.sigma_ref == pytest.approx(0.01, rel=0.2)


def test_robust_to_clutter_and_mixed_pixels() -> None:
    """15 % of the beams hit clutter in front of the walls or fall between two surfaces (40 % of the
    consecutive triples and 70 % of the 9-beam stretches are spoilt)."""
    rng = np.random.default_rng(11)
    lines = []
    for s in (random_room(seed, noise_sigma=0.01) for seed in range(8)):
        r = s.ranges.copy()
        ok = np.isfinite(r)
        hit = ok & (rng.uniform(size=r.size) < 0.15)
        r[hit] *= rng.uniform(0.3, 1.0, size=int(hit.sum()))
        lines.append(sg.Scanline.from_ranges(r, s.angles, s.times, range_min=s.range_min, range_max=s.range_max))
    assert estimate(lines).sigma_ref == pytest.approx(0.01, rel=0.2)


def test_quantisation_on_float32_lattice_with_offset() -> None:
    rng = np.random.default_rng(0)
    r = (0.0005 + 0.001 * rng.integers(300, 5000, 3000)).astype(np.float32).astype(np.float64)
    assert detect_quantum(r) == pytest.approx(0.001)
    assert detect_quantum(rng.uniform(0.3, 5.0, 3000)) == 0.0
    # no two values one step apart (few values, as in one scan): the step divides the smallest difference
    cm = np.concatenate((2 * rng.integers(15, 400, 100), 2 * rng.integers(420, 500, 12) + 1))
    assert detect_quantum(0.01 * cm) == 0.01


def test_noise_free_input_gives_the_floor() -> None:
    model = estimate(_rooms(0.0, n=2))
    assert model.sigma0 == pytest.approx(sg.noise.SIGMA_FLOOR) and model.slope == 0.0


def test_estimate_errors_and_per_scanner() -> None:
    a = _rooms(0.003, n=2)
    b = [dataclasses.replace(ln, scanner_id="rear") for ln in _rooms(0.02, n=2)]
    with pytest.raises(ValueError, match="several scanners"):
        estimate(a + b)
    models = estimate_per_scanner(a + b)
    assert models["scanner"].sigma_ref == pytest.approx(0.003, rel=0.2)
    assert models["rear"].sigma_ref == pytest.approx(0.02, rel=0.2)
    with pytest.raises(ValueError, match="no scanlines"):
        estimate([])
    few = sg.Scanline.from_ranges(np.ones(10), np.linspace(0, 0.1, 10))
    with pytest.raises(ValueError, match="need 30"):
        estimate(few)
    with pytest.raises(ValueError, match="sigma0"):
        NoiseModel.of(0.0, DEG)


def test_model_is_frozen_and_readable() -> None:
    model = estimate(_rooms(0.01, 0.01, n=3))
    with pytest.raises(dataclasses.FrozenInstanceError):
        model.sigma0 = 1.0  # type: ignore[misc]
    text = str(model)
    assert "range noise" in text and "mm at" in text and "quantisation 10 mm" in text
    assert "angular step 0.25 deg" in text and "from 3 scans" in text
    assert "stated, not estimated" in str(REFERENCE)


# ---- noise-derived defaults --------------------------------------------------------------------
def test_no_model_keeps_the_fixed_defaults() -> None:
    for name in sg.available():
        cls = sg.segmenter_class(name)
        assert sg.get(name).params == cls.Params(), name
        assert sg.get(name).noise is None
        # the reference scanner's model gives exactly the fixed defaults
        assert sg.get(name, noise=REFERENCE).params == cls.Params(), name
        assert cls.defaults(REFERENCE) == cls.defaults(), name
    ror = sg.get("ror").params
    assert (ror.sigma, ror.min_len, ror.point_sigma, ror.max_gap) == (0.0095, 15, 0.003, 0.2)  # type: ignore[attr-defined]


def test_model_scales_thresholds_and_counts() -> None:
    aces = NoiseModel.of(0.03, 1.0 * DEG)
    ror = sg.get("ror", noise=aces).params
    assert ror.sigma == pytest.approx(0.095)  # type: ignore[attr-defined]
    assert ror.point_sigma == 0.03 and ror.noise_slope == 0.0
    assert ror.min_len == sg.base.MIN_SEGMENT_POINTS  # 15 points at 0.25 deg span 0.31 m at 5 m: 5 beams at 1 deg
    assert ror.max_gap == pytest.approx(0.8)
    assert sg.get("line_tracking", noise=aces).params.threshold == pytest.approx(0.09)  # type: ignore[attr-defined]
    assert sg.get("iepf", noise=aces).params.threshold == pytest.approx(0.15)  # type: ignore[attr-defined]
    assert sg.get("split_and_merge", noise=aces).params.threshold == pytest.approx(0.11)  # type: ignore[attr-defined]
    assert sg.get("ransac", noise=aces).params.threshold == pytest.approx(0.1)  # type: ignore[attr-defined]
    hough = sg.get("hough", noise=aces).params
    assert hough.threshold == pytest.approx(0.1) and hough.rho_res == pytest.approx(0.2)  # type: ignore[attr-defined]
    sef = sg.get("sef", noise=aces).params
    assert sef.threshold == pytest.approx(0.4) and sef.corner_span == 1  # type: ignore[attr-defined]
    fine = sg.get("ror", noise=NoiseModel.of(0.003, 0.1 * DEG)).params
    assert fine.min_len == 36  # the same 0.31 m at 5 m at 0.1 deg
    growing = sg.get("ror", noise=NoiseModel.of(0.002, 0.25 * DEG, slope=0.001)).params
    assert growing.point_sigma == 0.002 and growing.noise_slope == 0.001


def test_explicit_parameters_win() -> None:
    model = NoiseModel.of(0.02, 1.0 * DEG)
    seg = sg.get("ror", noise=model, sigma=0.012, min_len=20)
    assert seg.params.sigma == 0.012 and seg.params.min_len == 20  # type: ignore[attr-defined]
    assert seg.params.point_sigma == 0.02 and seg.noise is model
    assert sg.auto(_rooms(0.01, n=2), "iepf", threshold=0.05).params.threshold == 0.05  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="NoiseModel"):
        sg.get("ror", noise="loud")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="'auto'"):
        sg.segment(np.ones((50, 2)), "ror", noise="loud")  # type: ignore[arg-type]


def test_auto_parameters_give_straight_segments_on_a_noisy_coarse_scanner() -> None:
    """An ACES-like scanner (1 deg steps, 2.5 cm noise, 1 cm quantisation): the fixed defaults find
    almost nothing, the auto parameters segment the walls, each segment on one face and straight."""
    spec = ScannerSpec(n_beams=180, angle_min=-90 * DEG, angle_increment=1.0 * DEG, noise_sigma=0.025,
                       quantization=0.01, range_min=0.1, range_max=30.0)
    scans = _office_scans(spec)
    lines = [line for _, line in scans]
    model = estimate(lines)
    assert model.sigma_ref == pytest.approx(math.sqrt(0.025**2 + 0.01**2 / 12), rel=0.2)
    for method in ("ror", "line_tracking", "split_and_merge", "iepf"):
        auto = sg.auto(lines, method)
        assert auto.noise is not None and auto.noise.sigma_ref == model.sigma_ref
        n_valid = n_auto = n_fixed = 0
        ratios, purities = [], []
        for s, line in scans:
            seg = auto.segment(line)
            lab = seg.labels[line.valid_index]
            n_valid += line.n_valid
            n_auto += int(np.count_nonzero(lab >= 0))
            n_fixed += int(np.count_nonzero(sg.segment(line, method).labels[line.valid_index] >= 0))
            face = np.asarray(s.face_ids)[line.valid_index]  # type: ignore[attr-defined]
            for k in range(seg.n_segments):
                f = face[lab == k]
                purities.append(np.max(np.bincount(f[f >= 0])) / f.size if np.any(f >= 0) else 0.0)
            r = np.hypot(seg.centroid[:, 0], seg.centroid[:, 1])
            ratios.extend(seg.rms / np.asarray(model.sigma(r)))
        assert n_auto / n_valid >= 0.6, method
        assert n_fixed / n_valid <= 0.2, method
        assert np.median(ratios) <= 1.5, method
        # on one face, but for a few beams at a corner (within the noise of both walls at 1 deg)
        assert np.median(purities) == 1.0 and np.mean(np.asarray(purities) >= 0.8) >= 0.9, method


def test_segment_auto_estimates_from_the_scan() -> None:
    s = random_room(4, noise_sigma=0.02)
    line = _line(s)
    res = sg.segment(line, "ror", noise="auto")
    model = estimate(line)
    assert res.params == dataclasses.asdict(sg.get("ror", noise=model).params)
    assert res.params["sigma"] == pytest.approx(0.0095 * model.sigma0 / 0.003)
    points = sg.segment(line.points_xy, "ror", noise="auto")  # an array of points: angles from the points
    assert points.params["sigma"] == pytest.approx(res.params["sigma"], rel=0.05)


# ---- the segment command -----------------------------------------------------------------------
def test_segment_command_prints_and_uses_the_model(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import json

    from backpack_slam.cli import main
    from slam.io.scanfile import write_npz

    spec = ScannerSpec(n_beams=180, angle_min=-90 * DEG, angle_increment=1.0 * DEG, noise_sigma=0.025,
                       quantization=0.01, range_min=0.1, range_max=30.0)
    path = write_npz(tmp_path / "scan.npz", _office_scans(spec, 1)[0][1])
    out_json = tmp_path / "auto.json"
    assert main(["segment", str(path), "--json", str(out_json), "--param", "min_len=9"]) == 0
    text = capsys.readouterr().out
    assert "noise model [scanner]: range noise" in text and "angular step 1 deg" in text
    data = json.loads(out_json.read_text())
    model = data["noise_models"]["scanner"]
    assert data["params"]["sigma"] == pytest.approx(0.0095 * model["sigma0"] / 0.003)
    assert data["params"]["min_len"] == 9  # explicit wins
    assert main(["segment", str(path), "--noise", "none", "--json", str(out_json)]) == 0
    assert "noise model" not in capsys.readouterr().out
    fixed = json.loads(out_json.read_text())
    assert fixed["params"] == sg.segmenter_class("ror").defaults() and fixed["noise_models"] == {}


def _correlated(lines: list[sg.Scanline], sigma: float, rho: float, seed: int = 0) -> list[sg.Scanline]:
    """``lines`` with AR(1) range errors along the scan: stationary std ``sigma``, neighbour correlation ``rho``."""
    rng = np.random.default_rng(seed)
    out = []
    for line in lines:
        e = np.empty(line.ranges.size)
        e[0] = rng.normal(0.0, sigma)
        kick = rng.normal(0.0, sigma * np.sqrt(1.0 - rho * rho), e.size)
        for i in range(1, e.size):
            e[i] = rho * e[i - 1] + kick[i]
        out.append(dataclasses.replace(line, ranges=line.ranges + e))
    return out


def test_ror_follows_the_independent_share_of_correlated_noise() -> None:
    white = estimate(_rooms(0.006))
    correlated = estimate(_correlated(_rooms(0.0), 0.006, 0.9))
    assert sg.base.independent_share(white) > 0.9
    assert sg.base.independent_share(correlated) < 0.8
    for model in (white, correlated):
        sigma = sg.get("ror", noise=model).params.sigma  # type: ignore[attr-defined]
        plain = sg.base.scaled_threshold(0.0095, model)
        assert sigma == pytest.approx(plain * sg.base.independent_share(model))
    # a model stated by hand has no beam-to-beam estimate: the paper's ratio
    assert sg.base.independent_share(NoiseModel.of(0.02, 1.0 * DEG)) == 1.0
