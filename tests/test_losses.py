"""Each loss on hand-made cases."""

import math

import pytest
import torch

from edygs_ns.losses.blur import blur_loss
from edygs_ns.losses.events import event_loss, log_intensity, predicted_event_count
from edygs_ns.losses.photometric import l1_dssim, latent_confidence
from edygs_ns.losses.regularizers import mask_consistency, mask_l1, motion_loss

THETA = 0.2
EPS = 1e-3


def _grey(value: torch.Tensor) -> torch.Tensor:
    """[H, W] grey levels -> [H, W, 3] RGB of that luma."""
    return value[..., None].repeat(1, 1, 3)


def test_event_loss_is_zero_when_renders_agree_with_events():
    torch.manual_seed(0)
    counts = torch.randint(-3, 4, (8, 10)).float()
    a = torch.rand(8, 10) * 0.5 + 0.2
    # I_b chosen so that ln(I_b + ε) − ln(I_a + ε) = Θ·E exactly
    b = (a + EPS) * torch.exp(THETA * counts) - EPS
    loss = event_loss(_grey(a), _grey(b), counts, THETA, EPS)
    assert loss.item() < 1e-5
    assert torch.allclose(predicted_event_count(_grey(a), _grey(b), THETA, EPS), counts, atol=1e-4)


def test_event_loss_measures_the_log_error_and_has_gradients():
    a = torch.full((4, 4), 0.5)
    b = torch.full((4, 4), 0.5, requires_grad=True)
    counts = torch.ones(4, 4)  # events say the log rose by one threshold, the renders say 0
    loss = event_loss(_grey(a), _grey(b), counts, THETA, EPS)
    assert math.isclose(loss.item(), THETA, rel_tol=1e-5)
    loss.backward()
    assert (b.grad < 0).all()  # raising I_b lowers the loss


def test_event_loss_is_finite_on_black_renders_and_rejects_bad_shapes():
    black = torch.zeros(3, 3, 3)
    assert torch.isfinite(log_intensity(black, EPS)).all()
    assert torch.isfinite(event_loss(black, black, torch.ones(3, 3), THETA, EPS))
    with pytest.raises(ValueError, match="event map"):
        event_loss(black, black, torch.ones(2, 3), THETA, EPS)
    with pytest.raises(ValueError, match="log_eps"):
        log_intensity(black, 0.0)


def test_l1_dssim_zero_for_identical_and_weighted_static_term():
    torch.manual_seed(0)
    img = torch.rand(16, 16, 3)
    assert l1_dssim(img, img, 0.2).item() < 1e-6
    other = torch.rand(16, 16, 3)
    full = l1_dssim(other, img, 0.0)
    assert torch.isclose(full, (other - img).abs().mean())
    # a mask of ones removes everything from the static term
    weight = torch.zeros(16, 16, 1)
    assert l1_dssim(other, img, 0.2, weight=weight).item() < 1e-6
    with pytest.raises(ValueError):
        l1_dssim(img, img[:8], 0.2)


def test_image_weights_scale_each_image_of_the_batch():
    torch.manual_seed(1)
    target = torch.rand(2, 16, 16, 3)
    pred = target.clone()
    pred[1] = torch.rand(16, 16, 3)  # only the second image is wrong
    plain = l1_dssim(pred, target, 0.2)
    assert torch.isclose(l1_dssim(pred, target, 0.2, image_weights=torch.ones(2)), plain, atol=1e-6)
    # the error sits in image 1: weighting it by 3 (and image 0 by anything) triples the loss
    assert torch.isclose(l1_dssim(pred, target, 0.2, image_weights=torch.tensor([0.5, 3.0])), 3 * plain, rtol=1e-4)
    assert l1_dssim(pred, target, 0.2, image_weights=torch.tensor([1.0, 0.0])).item() < 1e-6
    with pytest.raises(ValueError, match="image_weights"):
        l1_dssim(pred, target, 0.2, image_weights=torch.ones(3))


def test_latent_confidence_trusts_the_exposure_middle():
    index = torch.tensor([0, 1, 2, 3, 4, -1])
    flat = latent_confidence(index, 5, 0.0)
    assert torch.equal(flat, torch.ones(6))
    w = latent_confidence(index, 5, 4.0)
    assert torch.isclose(w[:5].mean(), torch.tensor(1.0))  # the loss keeps its scale
    assert w[2] > w[1] > w[0] and torch.isclose(w[0], w[4]) and torch.isclose(w[1], w[3])
    assert torch.isclose(w[2] / w[0], torch.tensor(5.0))  # 1 + a at the ends
    assert w[5] == 1.0  # not an EDI latent (a novel view or a blurry frame)
    with pytest.raises(ValueError, match="centre_weighting"):
        latent_confidence(index, 5, -1.0)


def test_static_term_pushes_mask_up_where_the_residual_is_large():
    pred = torch.zeros(8, 8, 3)
    target = torch.zeros(8, 8, 3)
    target[:4] = 1.0  # top half disagrees (a moving object), bottom half agrees
    mask = torch.full((8, 8, 1), 0.1, requires_grad=True)
    l1_dssim(pred, target, 0.0, weight=1 - mask).backward()
    assert (mask.grad[:4] < 0).all()  # descending raises M on the inconsistent half
    assert (mask.grad[4:] == 0).all()


def test_mask_regularisers():
    m = torch.tensor([[0.0, 0.5], [1.0, 0.5]])[..., None]
    assert math.isclose(mask_l1(m).item(), 0.5)
    assert mask_consistency(m, m.clone()).item() == 0.0
    assert math.isclose(mask_consistency(m, torch.zeros_like(m)).item(), 0.5)
    ref = torch.zeros_like(m, requires_grad=True)
    live = m.clone().requires_grad_(True)
    mask_consistency(live, ref).backward()
    assert ref.grad is None  # the reference is fixed
    assert live.grad is not None


def test_motion_loss_penalises_only_the_static_part():
    d_xyz = torch.ones(2, 3)
    d_rot = torch.zeros(2, 4)
    d_scale = torch.zeros(2, 3)
    static_vs_dynamic = torch.tensor([0.0, 1.0])
    # Gaussian 0 is static (m=0): its offset costs 3; Gaussian 1 is dynamic: free
    assert math.isclose(motion_loss(d_xyz, d_rot, d_scale, static_vs_dynamic).item(), 1.5)
    assert motion_loss(d_xyz, d_rot, d_scale, torch.ones(2)).item() == 0.0
    assert motion_loss(d_xyz[:0], d_rot[:0], d_scale[:0], torch.ones(0)).item() == 0.0


def test_blur_loss_is_zero_when_the_latents_average_to_the_blurry_frame():
    generator = torch.Generator().manual_seed(0)
    latents = torch.rand(2, 5, 4, 6, 3, generator=generator)
    assert blur_loss(latents, latents.mean(dim=1)).item() == 0.0
    # a per-colour error that EDI (grey ratios) cannot see is measured: red moved into one latent
    shifted = latents.clone()
    shifted[:, 0, ..., 0] += 0.5
    shifted[:, 1, ..., 0] -= 0.5
    assert blur_loss(shifted, latents.mean(dim=1)).item() == pytest.approx(0.0, abs=1e-6)
    brighter = latents + 0.1
    assert blur_loss(brighter, latents.mean(dim=1)).item() == pytest.approx(0.1, abs=1e-6)
    with pytest.raises(ValueError, match="blur_loss"):
        blur_loss(latents, latents.mean(dim=1)[:1])


def test_blur_loss_spreads_its_gradient_over_the_exposure():
    latents = torch.full((1, 4, 2, 2, 3), 0.5, requires_grad=True)
    blur_loss(latents, torch.full((1, 2, 2, 3), 0.4)).backward()
    # d/dR_j of |mean_j R_j - B| averaged over 12 values: 1 / (4 * 12) for every latent
    assert torch.allclose(latents.grad, torch.full_like(latents, 1.0 / 48))
