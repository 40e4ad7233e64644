"""The contrast threshold Θ from blurry frames and events: the fit, simulated captures, edygs-process."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import tyro
from PIL import Image

from edygs_ns.data.dataparser import EdygsDataParserConfig
from edygs_ns.events.contrast import (
    FALLBACK_THETA,
    MIN_PIXELS,
    ContrastAccumulator,
    choose_theta,
    estimate_contrast,
    fit_contrast,
)
from edygs_ns.events.exposures import Exposure, read_exposures
from edygs_ns.events.readers import read_events
from edygs_ns.events.types import EventArray
from edygs_ns.preprocess.inputs import InputConfig
from edygs_ns.preprocess.pipeline import ProcessConfig, ProcessEdiConfig, process
from edygs_ns.sim.writer import SynthConfig, write_synthetic_scene

#: Tiny simulated captures (a few seconds each); 9 sub-frames per blurry frame, the default.
TINY = dict(width=64, height=48, n_frames=6, supersample=1, sim_steps_per_exposure=12, novel_stride=6)
#: Thresholds of the issue, and the per-pixel spread as a fraction of Θ (0.1: 0.03 at Θ = 0.3).
THETAS = (0.15, 0.2, 0.3)
SIGMA_FRACTIONS = (0.0, 0.1)
#: Tolerance of every estimate (relative).
TOLERANCE = 0.10
K = 3


def _capture(root: Path, theta: float, sigma_fraction: float) -> Path:
    return write_synthetic_scene(SynthConfig(output_dir=root, contrast_threshold=theta,
                                             threshold_sigma=sigma_fraction * theta, **TINY))


def _linear_frames(exposures):
    return [np.asarray(Image.open(e.file).convert("RGB"), np.float32) / 255.0 for e in exposures]


@pytest.mark.parametrize("sigma_fraction", SIGMA_FRACTIONS)
@pytest.mark.parametrize("theta", THETAS)
def test_estimate_within_ten_percent_on_simulated_captures(tmp_path: Path, theta: float, sigma_fraction: float) -> None:
    raw = _capture(tmp_path / "raw", theta, sigma_fraction)
    exposures = read_exposures(raw / "exposures.csv")
    estimate = estimate_contrast(_linear_frames(exposures), exposures, read_events(raw / "events.h5"))
    assert estimate is not None
    for name in ("theta", "theta_pos", "theta_neg"):
        assert getattr(estimate, name) == pytest.approx(theta, rel=TOLERANCE), (name, estimate)
    assert estimate.n_pairs == TINY["n_frames"] - 1 and estimate.n_pixels >= MIN_PIXELS
    assert 0.0 <= estimate.spread < TOLERANCE * theta


def test_fit_recovers_distinct_polarity_thresholds_exactly() -> None:
    """Noise-free equations of the model: Θ+ and Θ− come back exactly, Θ lies between them."""
    rng = np.random.default_rng(0)
    s, m, theta_pos, theta_neg = 2000, 5, 0.27, 0.18
    steps = rng.poisson(0.6, size=(4, s, 2 * m - 1)).astype(np.float64)
    pos = np.concatenate([np.zeros((s, 1)), np.cumsum(steps[0], axis=1)], axis=1)
    neg = np.concatenate([np.zeros((s, 1)), np.cumsum(steps[1], axis=1)], axis=1)
    pos_p, pos_q, neg_p, neg_q = pos[:, :m], pos[:, m:], neg[:, :m], neg[:, m:]

    def log_mean(p, n):
        return np.log(np.exp(theta_pos * p - theta_neg * n).mean(axis=1))

    y = log_mean(pos_q, neg_q) - log_mean(pos_p, neg_p)
    estimate = fit_contrast(y, pos_p, neg_p, pos_q, neg_q, np.zeros(s, np.int64))
    assert estimate.theta_pos == pytest.approx(theta_pos, rel=1e-4)
    assert estimate.theta_neg == pytest.approx(theta_neg, rel=1e-4)
    assert theta_neg < estimate.theta < theta_pos


def test_static_scene_gives_no_estimate_and_the_fallback() -> None:
    frame = np.full((8, 10, 3), 0.5, np.float32)
    exposures = [Exposure(i, i * 100, i * 100 + 80, Path(f"{i}.png")) for i in range(3)]
    accumulator = ContrastAccumulator(len(exposures))
    for i, exposure in enumerate(exposures):
        accumulator.add(frame, exposure, EventArray.empty((8, 10)), exposure.start_us + 100)
    assert accumulator.estimate() is None and "usable pixels" in accumulator.reason()
    choice = choose_theta(None, None, accumulator.reason())
    assert (choice.theta, choice.source) == (FALLBACK_THETA, "fallback") and "--theta" in choice.line()
    assert choose_theta(None, 0.3).source == "given"
    with pytest.raises(ValueError, match="theta"):
        choose_theta(None, -0.1)


def test_theta_flag_defaults_to_estimating() -> None:
    assert ProcessConfig(output=Path("out")).edi.theta is None
    config = tyro.cli(ProcessConfig, args=["--output", "out", "--theta", "0.25"])
    assert config.edi.theta == 0.25


@pytest.fixture(scope="module")
def raw_03(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _capture(tmp_path_factory.mktemp("raw") / "capture", 0.3, 0.0)


def _process(raw: Path, output: Path, theta=None) -> dict:
    inputs = InputConfig(exposures=raw / "exposures.csv", events=raw / "events.h5")
    return process(ProcessConfig(output=output, inputs=inputs, edi=ProcessEdiConfig(k=K, theta=theta), poses="given",
                                 num_random_points=200))


def test_processed_scene_carries_the_estimate_and_the_dataparser_uses_it(raw_03: Path, tmp_path: Path) -> None:
    report = _process(raw_03, tmp_path / "scene")
    theta = json.loads((tmp_path / "scene" / "transforms.json").read_text())["theta"]
    assert report["theta_source"] == "estimated"
    assert theta == report["theta"] == report["theta_estimate"]["theta"]
    assert theta == pytest.approx(0.3, rel=TOLERANCE)
    outputs = EdygsDataParserConfig(data=tmp_path / "scene").setup().get_dataparser_outputs("train")
    assert outputs.metadata["theta"] == pytest.approx(theta)


def test_explicit_theta_wins_and_the_estimate_is_still_reported(raw_03: Path, tmp_path: Path) -> None:
    report = _process(raw_03, tmp_path / "scene", theta=0.2)
    assert json.loads((tmp_path / "scene" / "transforms.json").read_text())["theta"] == 0.2
    assert (report["theta"], report["theta_source"]) == (0.2, "given")
    assert report["theta_estimate"]["theta"] == pytest.approx(0.3, rel=TOLERANCE)
