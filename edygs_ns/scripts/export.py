"""Export the Gaussians of a trained EDyGS run at one time instant as a standard 3DGS PLY.

`edygs-export --load-config RUN/config.yml --output-dir DIR --time T` bakes the deformation at
time T (normalised to [0, 1] over the clip) into the Gaussians and writes the PLY layout of the
original 3D Gaussian Splatting code, which splat viewers read:

    x, y, z                      centre (deformed), world units of the dataparser frame
    nx, ny, nz                   zeros
    f_dc_0..2                    SH degree-0 coefficients (colour = 0.2821 f_dc + 0.5)
    f_rest_0..3*(B-1)-1          higher SH coefficients, channel-major (all R, then G, then B)
    opacity                      logit of the opacity
    scale_0..2                   log of the (deformed) scales
    rot_0..3                     unit quaternion (w, x, y, z) (deformed, renormalised)
    motion_mask                  extra: the motion-mask value m in [0, 1] (1 = dynamic)

Colours are in the pixel encoding the model was trained in: for "linear" scenes a viewer that
assumes sRGB shows them darker than our renders.

`ns-export gaussian-splat --load-config RUN/config.yml --output-dir DIR` also works (see
edygs_ns/model/splat_export_view.py): the same baked Gaussians, at the time $EDYGS_TIME or the
model config's `fallback_time` (default 0.0), with `motion_mask` too
(edygs_ns/model/ns_export_mask.py); nerfstudio drops Gaussians of opacity below 1/255.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import torch
import tyro
from nerfstudio.utils.rich_utils import CONSOLE

from edygs_ns.model.ns_export_mask import MOTION_MASK_PROPERTY
from edygs_ns.model.splat_export_view import bake_gaussians

#: Number of SH coefficients per colour channel at degree 0.
DC_COEFFS = 1
#: Binary PLY header pieces.
PLY_FORMAT = "format binary_little_endian 1.0"
PLY_FLOAT = "float"
#: Default output file name pattern (the time with TIME_DIGITS decimals).
FILENAME_PATTERN = "gaussians_t{time}.ply"
TIME_DIGITS = 3


@torch.no_grad()
def baked_gaussians(model: torch.nn.Module, time: float) -> "OrderedDict[str, np.ndarray]":
    """PLY columns of the model's Gaussians with the deformation baked at `time`.

    Args:
        model: an EdygsModel (needs `gauss_params` and `deformed_gaussians(time, deform)`).
        time: normalised time in [0, 1].

    Returns:
        Ordered property name -> float32 [N] array, in the order listed in the module docstring.
    """
    try:
        baked = bake_gaussians(model, time)
    except ValueError as err:
        raise ValueError(f"edygs-export: {err}") from None
    means = baked["means"].cpu()
    quats = baked["quats"].cpu()
    log_scales = baked["log_scales"].cpu()
    opacity = baked["opacity_logits"].reshape(-1).cpu()
    f_dc = baked["features_dc"].cpu()
    f_rest = baked["features_rest"].cpu()  # [N, B-1, 3]
    f_rest = f_rest.transpose(1, 2).reshape(means.shape[0], -1)  # channel-major, as 3DGS writes it
    columns: "OrderedDict[str, np.ndarray]" = OrderedDict()
    for i, axis in enumerate("xyz"):
        columns[axis] = means[:, i].numpy()
    for axis in ("nx", "ny", "nz"):
        columns[axis] = np.zeros(means.shape[0], dtype=np.float32)
    for i in range(f_dc.shape[1]):
        columns[f"f_dc_{i}"] = f_dc[:, i].numpy()
    for i in range(f_rest.shape[1]):
        columns[f"f_rest_{i}"] = f_rest[:, i].numpy()
    columns["opacity"] = opacity.numpy()
    for i in range(log_scales.shape[1]):
        columns[f"scale_{i}"] = log_scales[:, i].numpy()
    for i in range(quats.shape[1]):
        columns[f"rot_{i}"] = quats[:, i].numpy()
    columns[MOTION_MASK_PROPERTY] = baked["mask"].cpu().numpy()
    return OrderedDict((k, np.ascontiguousarray(v, dtype=np.float32)) for k, v in columns.items())


def write_gaussian_ply(path: Path, columns: "OrderedDict[str, np.ndarray]") -> Path:
    """Write float32 vertex properties [N] each as a binary little-endian PLY.

    Args:
        path: output file (parent folders created).
        columns: property name -> [N] array (written as float32, in this order).

    Returns:
        The path written.
    """
    if not columns:
        raise ValueError(f"write_gaussian_ply({path}): no property to write")
    counts = {name: int(np.asarray(v).size) for name, v in columns.items()}
    count = next(iter(counts.values()))
    if any(c != count for c in counts.values()):
        raise ValueError(f"write_gaussian_ply({path}): properties have different lengths {counts}")
    non_finite = sum(int((~np.isfinite(np.asarray(v))).sum()) for v in columns.values())
    if non_finite:
        CONSOLE.log(f"[yellow]write_gaussian_ply({path}): {non_finite} non-finite values written as they are")
    dtype = np.dtype([(name, "<f4") for name in columns])
    records = np.empty(count, dtype=dtype)
    for name, values in columns.items():
        records[name] = np.asarray(values, dtype=np.float32).reshape(-1)
    header = ["ply", PLY_FORMAT, "comment edygs_ns Gaussians", f"element vertex {count}"]
    header += [f"property {PLY_FLOAT} {name}" for name in columns]
    header.append("end_header")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as handle:
        handle.write(("\n".join(header) + "\n").encode("ascii"))
        handle.write(records.tobytes())
    return path


def export_gaussians(model: torch.nn.Module, path: Path, time: float) -> Path:
    """Bake the deformation at `time` and write the PLY to `path` (see the module docstring)."""
    columns = baked_gaussians(model, time)
    written = write_gaussian_ply(path, columns)
    CONSOLE.log(f"edygs-export: {columns['x'].size} Gaussians at t={time} -> {written}")
    return written


@dataclass
class ExportCommand:
    """Export the Gaussians of a trained EDyGS run at one time as a 3DGS PLY (with motion_mask)."""

    load_config: Path
    """The run's config.yml (written by ns-train)."""
    output_dir: Path = Path("exports")
    """Folder the PLY is written into (created)."""
    time: float = 0.0
    """Time to bake the deformation at, normalised to [0, 1] over the clip."""
    output_filename: Optional[str] = None
    """File name; default gaussians_t<time>.ply."""

    def main(self) -> Path:
        """Load the run and write the PLY; returns its path."""
        from nerfstudio.utils.eval_utils import eval_setup

        from edygs_ns.compat import allow_nerfstudio_checkpoints

        if not Path(self.load_config).is_file():
            raise FileNotFoundError(f"edygs-export: run config {self.load_config} does not exist (pass RUN/config.yml)")
        allow_nerfstudio_checkpoints()
        _, pipeline, _, _ = eval_setup(Path(self.load_config), test_mode="inference")
        pipeline.model.eval()
        name = self.output_filename or FILENAME_PATTERN.format(time=f"{self.time:.{TIME_DIGITS}f}")
        return export_gaussians(pipeline.model, Path(self.output_dir) / name, self.time)


def entrypoint() -> None:
    """Console script `edygs-export`."""
    tyro.cli(ExportCommand).main()


if __name__ == "__main__":
    entrypoint()
