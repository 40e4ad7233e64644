"""nerfstudio's own tools on EDyGS runs: `ns-export gaussian-splat` (the SplatfactoModel view of
the model, Gaussians baked at the fallback time) and `ns-render interpolate` (cameras without times
render at the fallback time)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.models.splatfacto import SplatfactoModel
from plyfile import PlyData
from test_eval_cli import DYNAMIC_LOGIT, HEAD_WEIGHT_STD, shared_tiny_run
from test_export import N_STATIC, _model

from edygs_ns.model.edygs_model import EdygsModel
from edygs_ns.model.ns_export_mask import MOTION_MASK_PROPERTY
from edygs_ns.model.splat_export_view import (
    EXPORT_PROPERTIES,
    INHERITED_HELPERS,
    SPLATFACTO_INTERNALS,
    TIME_ENV,
    bake_gaussians,
    resolve_time,
)

BIN = Path(sys.executable).parent
#: fallback_time written into the copied run's config.yml, and the $EDYGS_TIME given to the CLIs
#: (the environment wins).
CONFIG_TIME, ENV_TIME = 0.25, 0.5
#: ns-export drops Gaussians below this opacity logit (logit(1/255)).
EXPORT_MIN_OPACITY_LOGIT = -5.5373
#: poses ns-render interpolate puts between consecutive eval cameras.
INTERPOLATION_STEPS = 2
#: one 8-bit level: ns-render's PNGs against our float renders.
PNG_TOLERANCE = 1.0 / 255.0


@pytest.fixture(autouse=True)
def no_time_env(monkeypatch):
    monkeypatch.delenv(TIME_ENV, raising=False)


def _camera(times=None) -> Cameras:
    """One 32x24 camera 3 units in front of the test model's Gaussians (all in [-1, 1]^3)."""
    c2w = torch.tensor([[[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 3.0]]])
    return Cameras(camera_to_worlds=c2w, fx=20.0, fy=20.0, cx=16.0, cy=12.0, width=32, height=24, times=times)


# ------------------------------------------------------------------ the SplatfactoModel view
def test_every_splatfacto_attribute_is_replaced_or_a_pure_helper():
    assert issubclass(EdygsModel, SplatfactoModel)
    names = {n for n in vars(SplatfactoModel) if not n.startswith("__") or n == "__init__"}
    for name in names - INHERITED_HELPERS:
        owner = next(cls for cls in EdygsModel.__mro__ if name in vars(cls))
        assert owner is not SplatfactoModel, f"EdygsModel inherits SplatfactoModel.{name}"
    assert EXPORT_PROPERTIES | SPLATFACTO_INTERNALS | INHERITED_HELPERS <= names


def test_model_builds_without_splatfacto_and_refuses_its_internals(monkeypatch):
    def forbidden(self):
        raise AssertionError("SplatfactoModel.populate_modules ran")

    monkeypatch.setattr(SplatfactoModel, "populate_modules", forbidden)
    model = _model()  # test_export's tiny model, seed points given
    assert isinstance(model, SplatfactoModel) and model.num_points == model.means.shape[0]
    assert len(model.seed_points[0]) == model.num_points  # SplatfactoModel.__init__ did not reset them
    for call in (lambda: model.step_cb(None, 0), lambda: model.step_post_backward(0), model.get_gaussian_param_groups):
        with pytest.raises(NotImplementedError, match="splatfacto"):
            call()
    model.set_background(torch.ones(3))  # the viewer's call: ignored
    assert model.config.background_color == "black"


def test_properties_are_the_gaussians_baked_at_the_fallback_time(monkeypatch):
    model = _model()
    params = {k: v.detach() for k, v in model.gauss_params.items()}
    # default: t = 0.0
    torch.testing.assert_close(model.means, bake_gaussians(model, 0.0)["means"])
    monkeypatch.setenv(TIME_ENV, "1.0")
    baked = bake_gaussians(model, 1.0)
    for prop, key in (("means", "means"), ("scales", "log_scales"), ("quats", "quats")):
        value = getattr(model, prop)
        assert not value.requires_grad
        torch.testing.assert_close(value, baked[key])
    moved = (model.means - params["means"]).norm(dim=-1)
    assert torch.all(moved[:N_STATIC] == 0) and torch.all(moved[N_STATIC:] > 1e-4)  # only dynamic Gaussians move
    torch.testing.assert_close(model.opacities, params["opacities"])  # logits, as splatfacto stores them
    torch.testing.assert_close(model.shs_0, params["features_dc"])
    torch.testing.assert_close(model.shs_rest, params["features_rest"])
    torch.testing.assert_close(model.colors, params["features_dc"] * 0.28209479177387814 + 0.5)


def test_the_deformation_is_baked_once_per_export(monkeypatch):
    model = _model()
    calls = []
    real = model.deformed_gaussians
    monkeypatch.setattr(model, "deformed_gaussians", lambda *a, **k: calls.append(a) or real(*a, **k))
    first = model.means
    model.scales, model.quats, model.means
    assert len(calls) == 1  # one bake serves every property ns-export reads
    monkeypatch.setenv(TIME_ENV, "1.0")
    assert not torch.equal(model.means, first) and len(calls) == 2  # another time: baked again
    with torch.no_grad():
        model.gauss_params["means"].add_(0.5)  # an optimiser step changes the parameters in place
    torch.testing.assert_close(model.means, bake_gaussians(model, 1.0)["means"])
    assert len(calls) == 4  # baked again (and once by the reference bake_gaussians)


def test_time_comes_from_the_environment_then_the_config(monkeypatch):
    assert resolve_time(0.3) == 0.3
    monkeypatch.setenv(TIME_ENV, "0.75")
    assert resolve_time(0.3) == 0.75
    for bad in ("1.5", "-0.1", "nan", "soon"):
        monkeypatch.setenv(TIME_ENV, bad)
        with pytest.raises(ValueError, match=TIME_ENV):
            resolve_time(0.3)
    monkeypatch.delenv(TIME_ENV)
    with pytest.raises(ValueError, match="fallback_time"):
        resolve_time(2.0)


def test_cameras_without_times_render_at_the_fallback_time(monkeypatch):
    model = _model()
    model.config.fallback_time = 0.7
    timeless = model.get_outputs_for_camera(_camera())["rgb"]
    at = lambda t: model.get_outputs_for_camera(_camera(times=torch.tensor([[t]])))["rgb"]  # noqa: E731
    torch.testing.assert_close(timeless, at(0.7))
    assert (timeless - at(0.0)).abs().max() > 1e-3  # the time matters for this model
    monkeypatch.setenv(TIME_ENV, "0.0")
    torch.testing.assert_close(model.get_outputs_for_camera(_camera())["rgb"], at(0.0))


# ------------------------------------------------------------------ the host CLIs on a trained run
def _deformed_copy(config_path: Path, root: Path) -> Path:
    """Copy of a trained run whose every Gaussian deforms (training leaves the heads at zero), with
    fallback_time = CONFIG_TIME in its config.yml; returns the copy's config.yml."""
    config = yaml.load(config_path.read_text(), Loader=yaml.Loader)
    source = config.get_checkpoint_dir()
    config.output_dir = root / "runs"
    config.pipeline.model.fallback_time = CONFIG_TIME
    config.save_config()
    target = config.get_checkpoint_dir()
    target.mkdir(parents=True)
    gen = torch.Generator().manual_seed(0)
    for ckpt in sorted(source.glob("*.ckpt")):
        state = torch.load(ckpt, map_location="cpu", weights_only=False)
        model_state = state["pipeline"]
        logits = model_state["_model.gauss_params.mask_logit"]
        logits.copy_(DYNAMIC_LOGIT + 2.0 * torch.rand(logits.shape, generator=gen))  # every one deforms, m varies
        model_state["_model.deformation.head_xyz.weight"].normal_(0.0, HEAD_WEIGHT_STD, generator=gen)
        torch.save(state, target / ckpt.name)
    return config.get_base_dir() / "config.yml"


@pytest.fixture(scope="module")
def deformed_run(tmp_path_factory):
    """(config.yml, pipeline) of the deformed copy of the shared tiny run."""
    from nerfstudio.utils.eval_utils import eval_setup

    config = _deformed_copy(shared_tiny_run(tmp_path_factory), tmp_path_factory.mktemp("deformed"))
    _, pipeline, _, _ = eval_setup(config, test_mode="test")
    pipeline.model.eval()
    return config, pipeline


def _run(args, tmp_path: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONUNBUFFERED="1", OMP_WAIT_POLICY="PASSIVE", **{TIME_ENV: str(ENV_TIME)})
    result = subprocess.run([str(a) for a in args], capture_output=True, text=True, env=env, timeout=600, cwd=tmp_path)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return result


def test_ns_export_gaussian_splat_writes_the_baked_gaussians(deformed_run, tmp_path):
    config, pipeline = deformed_run
    out = tmp_path / "export"
    _run([BIN / "ns-export", "gaussian-splat", "--load-config", config, "--output-dir", out], tmp_path)
    vertex = PlyData.read(str(out / "splat.ply"))["vertex"]
    ply = {p.name: np.asarray(vertex[p.name]) for p in vertex.properties}

    model = pipeline.model
    baked = {k: v.cpu().numpy() for k, v in bake_gaussians(model, ENV_TIME).items()}
    keep = baked["opacity_logits"][:, 0] >= EXPORT_MIN_OPACITY_LOGIT
    assert keep.sum() > 0 and ply["x"].size == keep.sum() <= model.num_points
    xyz = np.stack([ply["x"], ply["y"], ply["z"]], axis=1)
    np.testing.assert_allclose(xyz, baked["means"][keep], atol=1e-6)
    np.testing.assert_allclose(np.stack([ply[f"scale_{i}"] for i in range(3)], 1), baked["log_scales"][keep], atol=1e-6)
    np.testing.assert_allclose(np.stack([ply[f"rot_{i}"] for i in range(4)], 1), baked["quats"][keep], atol=1e-6)
    # the motion mask rides along, row for row, although nerfstudio's exporter has no such column
    np.testing.assert_allclose(ply[MOTION_MASK_PROPERTY], baked["mask"][keep], atol=1e-7)
    assert np.ptp(ply[MOTION_MASK_PROPERTY]) > 0.01  # varies, so a row mix-up would show
    # the environment's time won over config.yml's, and the deformation moved the Gaussians
    canonical = model.gauss_params["means"].detach().numpy()[keep]
    at_config_time = bake_gaussians(model, CONFIG_TIME)["means"].cpu().numpy()[keep]
    assert np.abs(xyz - canonical).max() > 1e-3 and np.abs(xyz - at_config_time).max() > 1e-3


def test_ns_render_interpolate_renders_at_the_fallback_time(deformed_run, tmp_path):
    from nerfstudio.cameras.camera_paths import get_interpolated_camera_path
    from PIL import Image

    if shutil.which("ffmpeg") is None:
        pytest.fail("ffmpeg is required by ns-render; scripts/setup_env.sh installs it")
    config, pipeline = deformed_run
    out = tmp_path / "interp"
    _run([BIN / "ns-render", "interpolate", "--load-config", config, "--output-path", out, "--output-format", "images",
          "--image-format", "png", "--interpolation-steps", INTERPOLATION_STEPS, "--rendered-output-names", "rgb"],
         tmp_path)  # fmt: skip
    frames = sorted(out.glob("*.png"))
    eval_cameras = pipeline.datamanager.eval_dataset.cameras
    path = get_interpolated_camera_path(eval_cameras, INTERPOLATION_STEPS, order_poses=False)
    assert path.times is None and len(frames) == path.shape[0] > 0
    model = pipeline.model
    with torch.no_grad():
        for i in (0, len(frames) - 1):
            image = np.asarray(Image.open(frames[i]).convert("RGB"), dtype=np.float32) / 255.0
            camera = path[i : i + 1]
            expected = model.get_outputs_for_camera(camera)["rgb"].numpy()  # env unset: config.yml's time
            assert np.abs(image - expected).max() > 3 * PNG_TOLERANCE  # not the config's 0.25 ...
            camera.times = torch.full((1, 1), ENV_TIME)
            expected = model.get_outputs_for_camera(camera)["rgb"].numpy()
            np.testing.assert_allclose(image, expected, atol=PNG_TOLERANCE + 1e-6)  # ... but $EDYGS_TIME


#: Run in a fresh interpreter: imports nerfstudio's exporter in the order ``argv[1]`` names, builds
#: no model and reads no ``means``, then prints whether write_ply is wrapped and the module's class.
REGISTRATION_PROBE = """
import sys
if sys.argv[1] == "exporter-first":  # as ns-export: the exporter's own imports load the plugin
    import nerfstudio.scripts.exporter
else:  # the plugin first (ns-train, a Python script), the exporter later
    import nerfstudio.configs.method_configs
    assert "nerfstudio.scripts.exporter" not in sys.modules
    import nerfstudio.scripts.exporter
from nerfstudio.scripts.exporter import ExportGaussianSplat
from edygs_ns.model import ns_export_mask
assert ns_export_mask._source is None  # no model was built
print(ns_export_mask.is_installed(), type(sys.modules["nerfstudio.scripts.exporter"]).__name__)
"""


@pytest.mark.parametrize("order", ["exporter-first", "plugin-first"])
def test_the_mask_column_is_registered_when_the_plugin_loads(order):
    result = subprocess.run([sys.executable, "-c", REGISTRATION_PROBE, order], capture_output=True, text=True,
                            timeout=300, env=dict(os.environ, OMP_NUM_THREADS="1"))  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.split() == ["True", "module"]  # wrapped, and a plain module again


def test_exported_rows_match_a_filtered_subsequence():
    from edygs_ns.model.ns_export_mask import exported_rows

    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(50, 3)).astype(np.float32)
    keep = np.sort(rng.choice(50, size=30, replace=False))
    np.testing.assert_array_equal(exported_rows(xyz, xyz[keep]), keep)
    moved = xyz[keep].copy()
    moved[3, 0] += 1e-3  # a row that is not one of the model's centres
    assert exported_rows(xyz, moved) is None
    assert exported_rows(xyz[:0], xyz[:2]) is None
