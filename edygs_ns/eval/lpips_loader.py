"""LPIPS (Zhang et al. 2018) with AlexNet or VGG16 backbones, loaded from local files only.

LPIPS needs two sets of weights:

(a) the ImageNet backbone (torchvision's `alexnet-owt-7be5be79.pth` or `vgg16-397923af.pth`,
    61 MB / 528 MB). These are NOT shipped with any package; torchvision normally downloads them
    into the torch hub cache (`torch.hub.get_dir()/checkpoints`). This module never downloads:
    it builds the backbone with random weights and then loads the file it finds, looking in
    1. the `weights_path` argument (a .pth file, or a folder holding the file),
    2. the environment variable `EDYGS_LPIPS_WEIGHTS` (file or folder),
    3. the torch hub cache `torch.hub.get_dir()/checkpoints/` (`$TORCH_HOME/hub/checkpoints`),
    and raises `LpipsUnavailable` naming the file, where to put it and how to point at it.
(b) the small linear calibration layers (a few KB), which torchmetrics ships inside its package
    (`torchmetrics/functional/image/lpips_models/{alex,vgg}.pth`).

The network itself is torchmetrics' LPIPS module (`_NoTrainLpips`, a private class; if a later
torchmetrics changes it, loading raises `LpipsUnavailable` saying so rather than guessing).
Any state dict with torchvision's key names loads, so tests can use randomly initialised
backbones to exercise the loading path; meaningful LPIPS numbers need the real ImageNet weights.
"""

from __future__ import annotations

import inspect
import os
from pathlib import Path
from typing import Callable, Dict, List, Literal, Optional, Tuple, Union

import torch
from jaxtyping import Float
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

LpipsNet = Literal["alex", "vgg"]
LpipsFn = Callable[[Tensor, Tensor], Tensor]

#: Environment variable naming a backbone weights file or a folder holding them.
LPIPS_WEIGHTS_ENV = "EDYGS_LPIPS_WEIGHTS"
#: Command-line option of `edygs-eval` that passes `weights_path`.
LPIPS_CLI_OPTION = "--lpips-weights"
#: Folder under `torch.hub.get_dir()` where torchvision caches downloaded weights.
HUB_CHECKPOINTS_SUBDIR = "checkpoints"
#: torchvision model builder and weights enum for each LPIPS backbone name.
BACKBONES: Dict[str, Tuple[str, str]] = {"alex": ("alexnet", "AlexNet_Weights"), "vgg": ("vgg16", "VGG16_Weights")}
#: Key prefix of the convolutional trunk in torchvision's state dicts (the part LPIPS uses).
FEATURES_PREFIX = "features"
#: Smallest image side (pixels) the backbone's pooling stack accepts.
MIN_IMAGE_SIDE: Dict[str, int] = {"alex": 31, "vgg": 16}
#: Folder, inside torchmetrics' lpips module folder, that holds the linear-layer weights.
LINEAR_WEIGHTS_DIR = "lpips_models"
#: Number of colour channels expected in the last image axis.
NUM_CHANNELS = 3


class LpipsUnavailable(RuntimeError):
    """LPIPS cannot be computed here (weights file missing or unreadable, package missing)."""


def _check_net(net: str) -> None:
    if net not in BACKBONES:
        raise ValueError(f"LPIPS net must be one of {sorted(BACKBONES)}, got {net!r}")


def backbone_url(net: LpipsNet) -> str:
    """The URL torchvision would download the ImageNet backbone of `net` from."""
    _check_net(net)
    import torchvision

    weights_enum = getattr(torchvision.models, BACKBONES[net][1])
    return str(weights_enum.IMAGENET1K_V1.url)


def backbone_filename(net: LpipsNet) -> str:
    """File name of the backbone weights in the torch hub cache, e.g. 'alexnet-owt-7be5be79.pth'."""
    return backbone_url(net).rsplit("/", 1)[-1]


def hub_checkpoints_dir() -> Path:
    """`torch.hub.get_dir()/checkpoints`, where torchvision caches weights (honours $TORCH_HOME)."""
    return Path(torch.hub.get_dir()) / HUB_CHECKPOINTS_SUBDIR


def _candidates(net: LpipsNet, weights_path: Optional[Path]) -> List[Path]:
    """Files to try, in order: explicit path, environment variable, torch hub cache."""
    name = backbone_filename(net)
    roots: List[Path] = []
    if weights_path is not None:
        roots.append(Path(weights_path).expanduser())
    env_value = os.environ.get(LPIPS_WEIGHTS_ENV)
    if env_value:
        roots.append(Path(env_value).expanduser())
    out: List[Path] = []
    for root in roots:
        out.append(root if root.suffix == ".pth" or root.is_file() else root / name)
    out.append(hub_checkpoints_dir() / name)
    return out


def find_backbone_weights(net: LpipsNet, weights_path: Optional[Path] = None) -> Path:
    """Path of the local backbone weights file for `net`; no network access.

    Raises:
        LpipsUnavailable: no candidate exists; the message names the file, the folders searched,
            where to put the file, and the option / environment variable to point at it.
    """
    _check_net(net)
    tried = _candidates(net, weights_path)
    for path in tried:
        if path.is_file():
            return path
    name = backbone_filename(net)
    raise LpipsUnavailable(
        f"LPIPS({net}) needs the torchvision ImageNet backbone weights '{name}' "
        f"({backbone_url(net)}), which is not available locally (nothing is downloaded). "
        f"Looked for: {', '.join(str(p) for p in tried)}. "
        f"Put the file in {hub_checkpoints_dir()}/ , or pass {LPIPS_CLI_OPTION} PATH "
        f"(a .pth file or a folder holding it), or set {LPIPS_WEIGHTS_ENV}=PATH."
    )


def _load_backbone_state(net: LpipsNet, path: Path) -> Dict[str, Tensor]:
    """Read a torchvision state dict from `path`, keeping only the convolutional trunk."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # corrupt / truncated / not a torch file
        raise LpipsUnavailable(f"LPIPS({net}): cannot read backbone weights file {path}: {exc}") from exc
    if not isinstance(state, dict):
        raise LpipsUnavailable(f"LPIPS({net}): {path} does not hold a state dict (found {type(state).__name__})")
    return {k: v for k, v in state.items() if isinstance(k, str) and k.startswith(FEATURES_PREFIX + ".")}


class LpipsMetric:
    """LPIPS distance between image batches, a callable (pred, gt) -> [B].

    Attributes:
        net: backbone name, "alex" or "vgg".
        weights_file: the backbone weights file that was loaded.
        module: the torch module (frozen, eval mode); follows the inputs' device.
    """

    def __init__(self, net: LpipsNet, module: torch.nn.Module, weights_file: Path) -> None:
        self.net = net
        self.module = module
        self.weights_file = weights_file

    def __call__(self, pred: Float[Tensor, "*B H W 3"], gt: Float[Tensor, "*B H W 3"]) -> Float[Tensor, "B"]:
        """LPIPS per image (lower is more similar; 0 for identical images).

        Args:
            pred: [B, H, W, 3] (or [H, W, 3]) images in [0, 1]; gradients flow to it.
            gt: same shape, reference images in [0, 1].

        Returns:
            [B] LPIPS distances on pred's device.
        """
        if pred.dim() == 3:
            pred, gt = pred.unsqueeze(0), gt.unsqueeze(0)
        if pred.dim() != 4 or pred.shape[-1] != NUM_CHANNELS:
            raise ValueError(f"LPIPS: pred has shape {tuple(pred.shape)}, expected [B, H, W, 3]")
        if gt.shape != pred.shape:
            raise ValueError(f"LPIPS: gt has shape {tuple(gt.shape)}, pred has {tuple(pred.shape)}")
        min_side = MIN_IMAGE_SIDE[self.net]
        if min(pred.shape[1], pred.shape[2]) < min_side:
            raise ValueError(f"LPIPS({self.net}) needs images of at least {min_side}x{min_side} pixels, got {tuple(pred.shape[1:3])}")
        device = pred.device
        if next(self.module.parameters()).device != device:
            self.module.to(device)
        x = pred.permute(0, 3, 1, 2)
        y = gt.to(device=device, dtype=pred.dtype).permute(0, 3, 1, 2)
        return self.module(x, y, normalize=True).reshape(-1)


def _build_module(net: LpipsNet, backbone: Dict[str, Tensor], path: Path) -> torch.nn.Module:
    """torchmetrics' LPIPS with a random backbone, then our backbone tensors copied in."""
    try:
        from torchmetrics.functional.image import lpips as tm_lpips
    except ImportError as exc:
        raise LpipsUnavailable(f"LPIPS needs torchmetrics with torchvision installed: {exc}") from exc
    lin_file = Path(inspect.getfile(tm_lpips)).parent / LINEAR_WEIGHTS_DIR / f"{net}.pth"
    if not lin_file.is_file():
        raise LpipsUnavailable(f"LPIPS({net}): torchmetrics' linear-layer weights {lin_file} are missing")
    module_cls = getattr(tm_lpips, "_NoTrainLpips", None)
    if module_cls is None:
        raise LpipsUnavailable("LPIPS: this torchmetrics version has no _NoTrainLpips; edygs_ns.eval.lpips_loader needs updating")
    # pnet_rand=True: torchvision builds the backbone with weights=None, so nothing is downloaded.
    module = module_cls(pretrained=True, net=net, pnet_rand=True, model_path=str(lin_file))
    target = module.net.state_dict()  # keys "slice<k>.<index in features>.<param>"
    mapped: Dict[str, Tensor] = {}
    for key, tensor in target.items():
        _, index, param = key.split(".", 2)
        source_key = f"{FEATURES_PREFIX}.{index}.{param}"
        if source_key not in backbone:
            raise LpipsUnavailable(
                f"LPIPS({net}): {path} is not a torchvision {BACKBONES[net][0]} state dict (no '{source_key}')"
            )
        if tuple(backbone[source_key].shape) != tuple(tensor.shape):
            raise LpipsUnavailable(
                f"LPIPS({net}): {path} has '{source_key}' of shape {tuple(backbone[source_key].shape)}, "
                f"expected {tuple(tensor.shape)} ({BACKBONES[net][0]})"
            )
        mapped[key] = backbone[source_key]
    module.net.load_state_dict(mapped, strict=True)
    module.eval()
    for param in module.parameters():
        param.requires_grad_(False)
    return module


def load_lpips(
    net: LpipsNet, weights_path: Optional[Path] = None, device: Union[str, torch.device] = "cpu"
) -> LpipsMetric:
    """Build LPIPS for `net` from local weights, never touching the network.

    Args:
        net: "alex" (AlexNet, the common choice) or "vgg" (VGG16, the EDyGS authors' choice).
        weights_path: backbone .pth file or a folder holding it (see the module docstring for
            the search order).
        device: where the module lives at first; it then follows the inputs' device.

    Returns:
        A callable (pred [B, H, W, 3], gt [B, H, W, 3]) -> [B] LPIPS, differentiable in pred.
        Numbers are only meaningful with the real ImageNet backbone weights; any state dict
        with torchvision's keys loads (tests use random ones to check the loading path).

    Raises:
        LpipsUnavailable: weights missing or unreadable (the message says what to do).
        ValueError: `net` is not "alex" or "vgg".
    """
    path = find_backbone_weights(net, weights_path)
    backbone = _load_backbone_state(net, path)
    module = _build_module(net, backbone, path).to(device)
    return LpipsMetric(net, module, path)


def lpips_or_none(
    net: LpipsNet, weights_path: Optional[Path] = None, device: Union[str, torch.device] = "cpu"
) -> Tuple[Optional[LpipsMetric], str]:
    """`load_lpips`, or (None, reason) when it is unavailable, for "n/a" entries in tables.

    Returns:
        (metric, "") on success, (None, the LpipsUnavailable message) otherwise.
    """
    try:
        return load_lpips(net, weights_path, device), ""
    except LpipsUnavailable as exc:
        CONSOLE.log(f"[yellow]LPIPS({net}) unavailable: {exc}")
        return None, str(exc)
