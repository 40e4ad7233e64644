"""EDI against known truth (simulated blur + events), its exact algebra, and colour encodings."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from nerfstudio.utils.rich_utils import CONSOLE

from edygs_ns.events.accumulate import bin_events, latent_times_us
from edygs_ns.events.color import decode_to_linear, encode_from_linear, linear_to_srgb, srgb_to_linear
from edygs_ns.events.edi import EdiConfig, edi_from_frame, edi_latents
from edygs_ns.sim.simulator import SimulatorConfig, simulate_events

H, W = 40, 56
SUB_FRAMES = 33
EXPOSURE_US = 33_000
SHIFT_PX = 4.0
K = 5
THETA = 0.2
TEXTURE_WAVES = 6


def texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A detailed smooth texture in [0.05, 0.95]: a sum of random plane waves."""
    rng = np.random.default_rng(1)
    value = np.zeros_like(x)
    for _ in range(TEXTURE_WAVES):
        fx, fy = rng.uniform(-0.8, 0.8, 2)
        value += np.sin(fx * x + fy * y + rng.uniform(0, 2 * np.pi))
    return np.clip(0.5 + 0.45 * value / np.sqrt(TEXTURE_WAVES), 0.05, 0.95)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((a - b) ** 2)))


def test_edi_recovers_sharp_frames_from_simulated_blur_and_events():
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    sharp = np.stack([texture(xx - SHIFT_PX * i / (SUB_FRAMES - 1), yy) for i in range(SUB_FRAMES)])
    times = np.round(np.linspace(0, EXPOSURE_US, SUB_FRAMES)).astype(np.int64)
    events = simulate_events(sharp, times, SimulatorConfig(contrast_threshold=THETA))
    blurry = sharp.mean(axis=0)
    latent_t = latent_times_us(0, EXPOSURE_US, K)
    latents = edi_latents(blurry, bin_events(events, latent_t), THETA)
    assert latents.shape == (K, H, W)
    truth_index = np.searchsorted(times, latent_t)
    assert np.array_equal(times[truth_index], latent_t)
    psnr_latent = [psnr(latents[j], sharp[i]) for j, i in enumerate(truth_index)]
    psnr_blurry = [psnr(blurry, sharp[i]) for i in truth_index]
    CONSOLE.print(
        f"EDI vs sharp: latent PSNR {np.mean(psnr_latent):.2f} dB, blurry PSNR {np.mean(psnr_blurry):.2f} dB "
        f"(per latent {np.round(psnr_latent, 1).tolist()} vs {np.round(psnr_blurry, 1).tolist()})"
    )
    assert np.mean(psnr_latent) > np.mean(psnr_blurry) + 3.0
    assert all(pl > pb for pl, pb in zip(psnr_latent, psnr_blurry))


def test_edi_is_exact_when_events_match_the_model():
    rng = np.random.default_rng(0)
    bins = rng.integers(-3, 4, (K - 1, 6, 7)).astype(np.float32)
    first = rng.uniform(0.1, 0.5, (6, 7))
    s = np.concatenate([np.zeros((1, 6, 7)), np.cumsum(bins, axis=0)])
    truth = first[None] * np.exp(THETA * s)
    latents = edi_latents(truth.mean(axis=0), bins, THETA)
    np.testing.assert_allclose(latents, truth, rtol=1e-5)
    np.testing.assert_allclose(latents.mean(axis=0), truth.mean(axis=0), rtol=1e-5)


def test_edi_colour_channels_share_events():
    rng = np.random.default_rng(2)
    bins = rng.integers(-2, 3, (K - 1, 5, 4)).astype(np.float32)
    blurry = rng.uniform(0.1, 0.9, (5, 4, 3))
    colour = edi_latents(blurry, bins, THETA)
    assert colour.shape == (K, 5, 4, 3)
    for c in range(3):
        np.testing.assert_allclose(colour[..., c], edi_latents(blurry[..., c], bins, THETA), rtol=1e-6)


def test_edi_survives_huge_counts():
    bins = np.zeros((K - 1, 2, 2), np.float32)
    bins[:, 0, 0] = 2_000  # exp(0.2 * 8000) overflows without normalisation
    latents = edi_latents(np.full((2, 2), 0.5), bins, THETA)
    assert np.all(np.isfinite(latents))
    assert latents[-1, 0, 0] == pytest.approx(0.5 * K)


def test_edi_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="bins"):
        edi_latents(np.zeros((4, 4)), np.zeros((K - 1, 4, 5)), THETA)
    with pytest.raises(ValueError, match="bins for k=5"):
        edi_from_frame(np.zeros((4, 4), np.uint8), np.zeros((2, 4, 4)), EdiConfig())


def test_edi_config_defaults():
    config = EdiConfig()
    assert (config.k, config.theta, config.color_space, config.clip_max) == (5, 0.2, "linear", 1.0)


@pytest.mark.parametrize("color_space", ["linear", "srgb"])
def test_edi_from_frame_without_events_returns_the_frame(color_space):
    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, (6, 5, 3), dtype=np.uint8)
    latents = edi_from_frame(image, np.zeros((K - 1, 6, 5)), EdiConfig(color_space=color_space))
    assert latents.shape == (K, 6, 5, 3) and latents.dtype == np.float32
    for j in range(K):
        np.testing.assert_allclose(latents[j], image / 255.0, atol=1e-5)


def test_edi_from_frame_srgb_applies_events_in_linear_space_and_clips():
    image = np.full((2, 2), 0.5, dtype=np.float32)
    bins = np.zeros((K - 1, 2, 2), np.float32)
    bins[0, 0, 0] = 5  # latents 1.. of pixel (0, 0) are brighter by exp(1) in linear intensity
    bins[0, 1, 1] = -40  # latent 0 holds almost all of the exposure's light: 5x, clipped
    out = edi_from_frame(image, bins, EdiConfig(color_space="srgb"))
    linear = edi_latents(srgb_to_linear(image), bins, THETA)
    np.testing.assert_allclose(out[:, 0, 0], linear_to_srgb(np.clip(linear[:, 0, 0], 0, 1)), rtol=1e-5)
    assert out[1, 0, 0] / out[0, 0, 0] != pytest.approx(np.e, rel=1e-3)  # not applied to sRGB values
    assert linear[1, 0, 0] / linear[0, 0, 0] == pytest.approx(np.e, rel=1e-5)
    assert linear[0, 1, 1] > 1.0
    assert out.max() <= 1.0 and out[0, 1, 1] == pytest.approx(1.0)


def test_srgb_transfer_known_values_and_inverse_numpy_and_torch():
    assert srgb_to_linear(np.array(0.5)) == pytest.approx(0.214041, abs=1e-5)
    assert linear_to_srgb(np.array(0.0031308 / 2)) == pytest.approx(0.0031308 / 2 * 12.92)
    x = np.linspace(0, 1, 101)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-6)
    xt = torch.linspace(0, 1, 101)
    back = linear_to_srgb(srgb_to_linear(xt))
    assert isinstance(back, torch.Tensor)
    torch.testing.assert_close(back, xt, atol=1e-5, rtol=0)
    torch.testing.assert_close(srgb_to_linear(xt), torch.from_numpy(srgb_to_linear(x)).float(), atol=1e-6, rtol=0)


def test_decode_encode_dispatch():
    x = np.array([0.2, 0.7])
    assert decode_to_linear(x, "linear") is x and encode_from_linear(x, "linear") is x
    np.testing.assert_allclose(decode_to_linear(x, "srgb"), srgb_to_linear(x))
    np.testing.assert_allclose(encode_from_linear(x, "srgb"), linear_to_srgb(x))
    with pytest.raises(ValueError, match="color_space"):
        decode_to_linear(x, "gamma22")  # type: ignore[arg-type]
