"""edygs-export: a standard 3DGS PLY with the deformation baked at a time, plus motion_mask."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch
from plyfile import PlyData
from test_eval_cli import shared_tiny_run

from edygs_ns.model.appearance import SH_C0
from edygs_ns.model.deformation import DeformationConfig
from edygs_ns.model.edygs_model import EdygsModelConfig
from edygs_ns.scripts.export import MOTION_MASK_PROPERTY, baked_gaussians, export_gaussians

#: Tiny model: Gaussians, SH degree, and how many of them are made clearly static.
N_GAUSSIANS = 40
SH_DEGREE = 2
N_STATIC = 10
#: Std of the random deformation-head weights and the head bias set in the test.
HEAD_WEIGHT_STD = 0.5
HEAD_BIAS = 0.05
#: Mask logits of the static Gaussians (m ~ 0) and of the dynamic ones (m ~ 0.95, above the
#: model's deform_mask_threshold, so the deformation applies to them).
STATIC_LOGIT, DYNAMIC_LOGIT = -10.0, 3.0


def _model():
    from nerfstudio.data.scene_box import SceneBox

    gen = torch.Generator().manual_seed(0)
    points = torch.rand(N_GAUSSIANS, 3, generator=gen) * 2.0 - 1.0
    config = EdygsModelConfig(
        sh_degree=SH_DEGREE, deformation=DeformationConfig(depth=2, width=16, skip_layer=0, xyz_frequencies=2, time_frequencies=2)
    )
    model = config.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3])), num_train_data=3, metadata={},
                         seed_points=(points, None))  # fmt: skip
    with torch.no_grad():
        for head in (model.deformation.head_xyz, model.deformation.head_rot, model.deformation.head_scale):
            head.weight.normal_(0.0, HEAD_WEIGHT_STD, generator=gen)
            head.bias.fill_(HEAD_BIAS)
        model.gauss_params["features_rest"].normal_(generator=gen)
        model.gauss_params["mask_logit"][:N_STATIC] = STATIC_LOGIT
        model.gauss_params["mask_logit"][N_STATIC:] = DYNAMIC_LOGIT
    assert torch.sigmoid(torch.tensor(DYNAMIC_LOGIT)) > model.config.deform_mask_threshold
    model.eval()
    return model


def _expected_properties(n_rest: int) -> list:
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(n_rest)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3", MOTION_MASK_PROPERTY]
    return names


def _read(path) -> dict:
    vertex = PlyData.read(str(path))["vertex"]
    return {p.name: np.asarray(vertex[p.name]) for p in vertex.properties}


def test_ply_has_the_3dgs_layout_and_values(tmp_path):
    model = _model()
    path = export_gaussians(model, tmp_path / "t0.ply", time=0.0)
    ply = _read(path)
    n_rest = 3 * ((SH_DEGREE + 1) ** 2 - 1)
    assert list(ply) == _expected_properties(n_rest)
    assert all(v.shape == (N_GAUSSIANS,) and v.dtype == np.float32 for v in ply.values())
    params = {k: v.detach().numpy() for k, v in model.gauss_params.items()}
    static = slice(0, N_STATIC)  # not deformed: the PLY holds the canonical values
    np.testing.assert_allclose(np.stack([ply["x"], ply["y"], ply["z"]], 1)[static], params["means"][static], atol=1e-6)
    np.testing.assert_allclose(np.stack([ply[f"scale_{i}"] for i in range(3)], 1)[static], params["scales"][static], atol=1e-5)
    np.testing.assert_allclose(ply["opacity"], params["opacities"][:, 0], atol=1e-6)
    np.testing.assert_allclose(ply[MOTION_MASK_PROPERTY], 1.0 / (1.0 + np.exp(-params["mask_logit"][:, 0])), atol=1e-6)
    quats = np.stack([ply[f"rot_{i}"] for i in range(4)], 1)
    np.testing.assert_allclose(np.linalg.norm(quats, axis=1), 1.0, atol=1e-5)
    # f_rest is channel-major: all coefficients of red, then green, then blue
    rest = params["features_rest"]  # [N, B-1, 3]
    n_bases = rest.shape[1]
    np.testing.assert_allclose(ply[f"f_rest_{n_bases + 2}"], rest[:, 2, 1], atol=1e-6)
    np.testing.assert_array_equal(ply["nx"], 0.0)


def test_baking_at_two_times_moves_only_the_deformed_gaussians():
    model = _model()
    early, late = baked_gaussians(model, 0.0), baked_gaussians(model, 1.0)
    xyz = lambda c: np.stack([c["x"], c["y"], c["z"]], 1)  # noqa: E731
    moved = np.linalg.norm(xyz(early) - xyz(late), axis=1)
    assert np.all(moved[:N_STATIC] == 0.0)
    assert np.all(moved[N_STATIC:] > 1e-4)
    scales = lambda c: np.stack([c[f"scale_{i}"] for i in range(3)], 1)  # noqa: E731
    assert not np.allclose(scales(early)[N_STATIC:], scales(late)[N_STATIC:])


def test_the_colour_offset_is_baked_into_the_dc_term_of_the_deformed_gaussians():
    from dataclasses import replace

    from edygs_ns.model.splat_export_view import bake_gaussians

    plain = _model()
    model = _model()
    model.config.deformation = replace(model.config.deformation, colour=True)
    model.deformation = type(model.deformation)(model.config.deformation)
    state = plain.deformation.state_dict()
    model.deformation.prepare_load(state, "")  # the plain model's heads, a zero colour head
    model.deformation.load_state_dict(state)
    with torch.no_grad():
        model.deformation.head_colour.bias.copy_(torch.tensor([0.1, -0.05, 0.02]))
    before, after = bake_gaussians(plain, 0.4), bake_gaussians(model, 0.4)
    shift = (after["features_dc"] - before["features_dc"]) * SH_C0  # RGB units
    assert torch.allclose(shift[:N_STATIC], torch.zeros(N_STATIC, 3))
    assert torch.allclose(shift[N_STATIC:], torch.tensor([0.1, -0.05, 0.02]).expand(N_GAUSSIANS - N_STATIC, 3), atol=1e-3)
    assert torch.equal(after["means"], before["means"])


def test_time_outside_the_clip_is_rejected():
    with pytest.raises(ValueError, match="time"):
        baked_gaussians(_model(), 1.5)


def test_cli_exports_a_trained_run(tmp_path, tmp_path_factory, monkeypatch):
    from nerfstudio.utils.eval_utils import eval_setup

    from edygs_ns.scripts import export

    config = shared_tiny_run(tmp_path_factory)
    out = tmp_path / "export"
    monkeypatch.setattr(sys, "argv", ["edygs-export", "--load-config", str(config), "--output-dir", str(out), "--time", "0.5"])
    export.entrypoint()
    ply = _read(out / "gaussians_t0.500.ply")
    _, pipeline, _, _ = eval_setup(config, test_mode="inference")
    assert ply["x"].size == pipeline.model.num_points
    assert MOTION_MASK_PROPERTY in ply
