"""Tests for edygs_ns.eval.metrics and edygs_ns.eval.lpips_loader."""

from __future__ import annotations

import math
import socket
import urllib.request

import pytest
import torch

from edygs_ns.eval import lpips_loader
from edygs_ns.eval.lpips_loader import LpipsUnavailable, backbone_filename, load_lpips, lpips_or_none
from edygs_ns.eval.metrics import MetricSet
from edygs_ns.losses.metrics import mask_iou, psnr, ssim, ssim_map

SIZE = 32


def _images(seed: int = 0, batch: int = 2) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    # smooth-ish content so SSIM is meaningful: low-res noise upsampled
    low = torch.rand(batch, 3, SIZE // 4, SIZE // 4, generator=gen)
    img = torch.nn.functional.interpolate(low, size=(SIZE, SIZE), mode="bilinear", align_corners=False)
    return img.permute(0, 2, 3, 1).contiguous()


# ---------------------------------------------------------------- PSNR


def test_psnr_identical_is_inf():
    x = _images()
    assert psnr(x, x) == math.inf


def test_psnr_constant_offset_known_value():
    x = _images() * 0.5
    offset = 0.1
    value = psnr(x + offset, x)
    assert value == pytest.approx(10.0 * math.log10(1.0 / offset**2), abs=1e-4)  # 20 dB
    assert psnr(x[0] + offset, x[0]) == pytest.approx(value, abs=1e-4)  # [H, W, 3] accepted


def test_psnr_mask_counts_only_selected_pixels():
    x = _images(batch=1)[0] * 0.5
    y = x.clone()
    y[: SIZE // 2] += 0.2  # top half wrong by 0.2, bottom half exact
    mask = torch.zeros(SIZE, SIZE, dtype=torch.bool)
    mask[: SIZE // 2] = True
    assert psnr(y, x, mask=mask) == pytest.approx(10.0 * math.log10(1.0 / 0.2**2), abs=1e-4)
    assert psnr(y, x, mask=~mask) == math.inf
    with pytest.raises(ValueError, match="no pixel"):
        psnr(y, x, mask=torch.zeros(SIZE, SIZE, dtype=torch.bool))


def test_psnr_shape_mismatch_raises():
    with pytest.raises(ValueError, match="gt has shape"):
        psnr(torch.rand(8, 8, 3), torch.rand(8, 9, 3))


# ---------------------------------------------------------------- SSIM


def test_ssim_identity_and_monotone_in_noise():
    x = _images()
    assert ssim(x, x) == pytest.approx(1.0, abs=1e-6)
    gen = torch.Generator().manual_seed(1)
    noise = torch.randn(x.shape, generator=gen)
    values = [ssim((x + level * noise).clamp(0, 1), x) for level in (0.01, 0.05, 0.2)]
    assert 1.0 > values[0] > values[1] > values[2]


def test_ssim_rejects_images_smaller_than_window():
    with pytest.raises(ValueError, match="window"):
        ssim(torch.rand(8, 8, 3), torch.rand(8, 8, 3))


def _noisy_pair(seed: int = 3):
    x = _images(seed=seed)
    gen = torch.Generator().manual_seed(seed + 1)
    y = (x + 0.1 * torch.randn(x.shape, generator=gen)).clamp(0, 1)
    return y, x


def test_ssim_matches_torchmetrics_reflect_and_valid():
    tm_image = pytest.importorskip("torchmetrics.image")
    y, x = _noisy_pair()
    reference = tm_image.StructuralSimilarityIndexMeasure(data_range=1.0, kernel_size=11, sigma=1.5, k1=0.01, k2=0.03)
    expected_reflect = float(reference(y.permute(0, 3, 1, 2), x.permute(0, 3, 1, 2)))
    assert ssim(y, x, padding="reflect") == pytest.approx(expected_reflect, abs=1e-4)
    # torchmetrics' full map is computed on reflect-padded images: its interior is the valid SSIM
    full = tm_image.StructuralSimilarityIndexMeasure(data_range=1.0, return_full_image=True)
    _, full_map = full(y.permute(0, 3, 1, 2), x.permute(0, 3, 1, 2))
    half = 5
    expected_valid = float(full_map[..., half:-half, half:-half].mean())
    assert ssim(y, x, padding="valid") == pytest.approx(expected_valid, abs=1e-4)
    assert abs(expected_valid - expected_reflect) > 1e-3  # the two conventions really differ here


def test_ssim_paddings_agree_in_the_interior():
    y, x = _noisy_pair(seed=7)
    valid = ssim_map(y, x, "valid")
    assert valid.shape == (2, 3, SIZE - 10, SIZE - 10)
    for padding in ("reflect", "zero"):
        same = ssim_map(y, x, padding)
        assert same.shape == (2, 3, SIZE, SIZE)
        assert torch.allclose(same[..., 5:-5, 5:-5], valid, atol=1e-5)
    # zero padding darkens the border, so it changes the border SSIM
    assert not torch.allclose(ssim_map(y, x, "zero"), ssim_map(y, x, "reflect"), atol=1e-3)
    with pytest.raises(ValueError, match="padding"):
        ssim(y, x, padding="same")


# ---------------------------------------------------------------- mask IoU


def test_mask_iou_hand_made():
    pred = torch.zeros(4, 4)
    pred[0, :] = 0.9  # 4 pixels predicted
    pred[1, 0] = 0.6  # 5th predicted pixel
    pred[2, :] = 0.4  # below threshold
    gt = torch.zeros(4, 4, dtype=torch.bool)
    gt[0, :2] = True
    gt[3, 3] = True
    # intersection 2, union 4 + 1 + 1 = 6
    assert mask_iou(pred, gt) == pytest.approx(2 / 6)
    assert mask_iou(pred, gt, threshold=0.3) == pytest.approx(2 / 10)
    assert mask_iou(gt.float(), gt) == 1.0


def test_mask_iou_empty_union_is_one_and_disjoint_is_zero():
    empty = torch.zeros(3, 3, dtype=torch.bool)
    assert mask_iou(torch.zeros(3, 3), empty) == 1.0
    gt = empty.clone()
    gt[0, 0] = True
    pred = torch.zeros(3, 3)
    pred[2, 2] = 1.0
    assert mask_iou(pred, gt) == 0.0


# ---------------------------------------------------------------- MetricSet


def test_metric_set_mean_std():
    ms = MetricSet()
    for value in (1.0, 2.0, 3.0, 4.0):
        ms.update({"psnr": value, "ssim": value / 10})
    assert ms.count("psnr") == 4
    assert ms.mean("psnr") == pytest.approx(2.5)
    assert ms.std("psnr") == pytest.approx(math.sqrt(1.25))
    summary = ms.summary()
    assert summary["ssim"]["mean"] == pytest.approx(0.25)
    assert summary["ssim"]["n"] == 4
    with pytest.raises(KeyError, match="lpips"):
        ms.mean("lpips")


# ---------------------------------------------------------------- LPIPS


@pytest.fixture
def offline_hub(tmp_path, monkeypatch):
    """A torch hub cache in tmp_path, no env override, and any network attempt fails loudly."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    monkeypatch.delenv(lpips_loader.LPIPS_WEIGHTS_ENV, raising=False)
    monkeypatch.setattr(torch.hub, "_hub_dir", None, raising=False)

    def no_network(*args, **kwargs):
        raise AssertionError(f"network access attempted: {args[:2]}")

    monkeypatch.setattr(socket.socket, "connect", no_network)
    monkeypatch.setattr(urllib.request, "urlopen", no_network)
    monkeypatch.setattr(torch.hub, "download_url_to_file", no_network)
    return tmp_path / "torch_home" / "hub" / "checkpoints"


def test_lpips_unavailable_names_file_and_remedy(offline_hub):
    with pytest.raises(LpipsUnavailable) as info:
        load_lpips("alex")
    message = str(info.value)
    assert "alexnet-owt-7be5be79.pth" in message
    assert str(offline_hub) in message
    assert lpips_loader.LPIPS_WEIGHTS_ENV in message and lpips_loader.LPIPS_CLI_OPTION in message
    metric, reason = lpips_or_none("vgg")
    assert metric is None and "vgg16-397923af.pth" in reason


def test_lpips_rejects_wrong_state_dict(offline_hub, tmp_path):
    bad = tmp_path / "bad.pth"
    torch.save({"features.0.weight": torch.zeros(1)}, bad)
    with pytest.raises(LpipsUnavailable, match="bad.pth"):
        load_lpips("alex", weights_path=bad)


def test_lpips_loads_backbone_from_hub_cache(offline_hub):
    torchvision = pytest.importorskip("torchvision")
    torch.manual_seed(0)
    offline_hub.mkdir(parents=True)
    state = torchvision.models.alexnet(weights=None).state_dict()
    torch.save(state, offline_hub / backbone_filename("alex"))

    metric = load_lpips("alex")
    assert metric.weights_file == offline_hub / "alexnet-owt-7be5be79.pth"
    # the loaded backbone is exactly the file's tensors
    assert torch.equal(metric.module.net.slice1[0].weight, state["features.0.weight"])

    x = _images(seed=5)
    gen = torch.Generator().manual_seed(6)
    noise = torch.rand(x.shape, generator=gen)
    same = metric(x, x)
    assert same.shape == (2,)
    assert torch.allclose(same, torch.zeros(2), atol=1e-6)
    pred = noise.clone().requires_grad_(True)
    dist = metric(pred, x)
    assert bool((dist > 0).all())
    dist.sum().backward()
    assert pred.grad is not None and float(pred.grad.abs().sum()) > 0


def test_lpips_explicit_path_env_var_and_size_check(offline_hub, tmp_path, monkeypatch):
    torchvision = pytest.importorskip("torchvision")
    folder = tmp_path / "weights"
    folder.mkdir()
    weights_file = folder / backbone_filename("alex")
    torch.save(torchvision.models.alexnet(weights=None).state_dict(), weights_file)
    # not in the hub cache: found through the argument (folder or file) or the environment variable
    metric, reason = lpips_or_none("alex", weights_path=folder)
    assert reason == "" and metric is not None and metric.weights_file == weights_file
    assert load_lpips("alex", weights_path=weights_file).weights_file == weights_file
    monkeypatch.setenv(lpips_loader.LPIPS_WEIGHTS_ENV, str(folder))
    assert load_lpips("alex").weights_file == weights_file
    with pytest.raises(ValueError, match="at least 31"):
        metric(torch.rand(1, 16, 16, 3), torch.rand(1, 16, 16, 3))
