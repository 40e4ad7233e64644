"""The CPU rasteriser against a brute-force float64 evaluation of the splatting equations."""

from __future__ import annotations

import math
import weakref
from typing import Dict, Tuple

import pytest
import torch
from torch import Tensor

from edygs_ns.render.contract import ALPHA_MAX, ALPHA_MIN, LOW_PASS_EPS, TRANSMITTANCE_MIN, select_backend
from edygs_ns.render.projection import project_gaussians, project_gaussians_autograd
import edygs_ns.render.torch_backend as torch_backend
from edygs_ns.render.torch_backend import TILE_SIZE, bin_gaussians, rasterize_torch

WIDTH, HEIGHT = 21, 14  # not multiples of the tile size: exercises the cropped edge tiles
PARAM_NAMES = ("means", "quats", "scales", "opacities", "features", "viewmats")
WALL_OPACITY = 0.99999  # above ALPHA_MAX: the clamp happens at the wall centres


pytestmark = pytest.mark.usefixtures("one_thread")


def look_at_viewmat(eye: Tensor, target: Tensor) -> Tensor:
    """World-to-camera (OpenCV: x right, y down, z forward) looking from eye to target."""
    forward = (target - eye) / (target - eye).norm()
    right = torch.linalg.cross(forward, torch.tensor([0.0, -1.0, 0.0], dtype=eye.dtype))
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    rot = torch.stack([right, down, forward])  # rows: camera axes in world coordinates
    view = torch.eye(4, dtype=eye.dtype)
    view[:3, :3] = rot
    view[:3, 3] = -rot @ eye
    return view


def make_scene(n: int, n_cams: int, seed: int, channels: int = 4, walls: bool = True) -> Dict[str, Tensor]:
    """Random Gaussians around the origin seen by n_cams cameras, float64.

    With ``walls`` three large nearly opaque Gaussians sit behind each other so the alpha clamp
    and the transmittance cut-off both happen (``brute_render`` counts the cut-off pixels).
    """
    g = torch.Generator().manual_seed(seed)
    dt = torch.float64
    means = (torch.rand(n, 3, generator=g, dtype=dt) - 0.5) * torch.tensor([3.0, 2.2, 1.5], dtype=dt)
    scales = 0.04 + 0.25 * torch.rand(n, 3, generator=g, dtype=dt)
    quats = torch.randn(n, 4, generator=g, dtype=dt)
    opacities = 0.2 + 0.75 * torch.rand(n, generator=g, dtype=dt)
    features = torch.rand(n, channels, generator=g, dtype=dt)
    if walls:  # flat discs facing the first camera
        means[:3] = torch.tensor([[0.1, 0.0, -0.6], [0.0, 0.1, -0.4], [-0.1, 0.0, -0.2]], dtype=dt)
        scales[:3] = torch.tensor([2.0, 1.5, 0.05], dtype=dt)
        quats[:3] = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=dt)
        opacities[:3] = WALL_OPACITY
    viewmats, ks = [], []
    for c in range(n_cams):
        angle = 0.3 * c
        eye = torch.tensor([3.0 * math.sin(angle), 0.3, -3.0 * math.cos(angle)], dtype=dt)
        viewmats.append(look_at_viewmat(eye, torch.zeros(3, dtype=dt)))
        ks.append(torch.tensor([[18.0 + c, 0.0, WIDTH / 2 + 0.3], [0.0, 17.0, HEIGHT / 2 - 0.2], [0.0, 0.0, 1.0]], dtype=dt))
    return {
        "means": means, "quats": quats, "scales": scales, "opacities": opacities, "features": features,
        "viewmats": torch.stack(viewmats), "Ks": torch.stack(ks),
    }


# ----------------------------------------------------------------------------- brute force
def brute_project(scene: Dict[str, Tensor], width: int, height: int):
    """EWA projection written out with explicit 3x3 / 2x3 matrices (float64)."""
    q = scene["quats"] / scene["quats"].norm(dim=-1, keepdim=True)
    w, v = q[:, 0], q[:, 1:]
    skew = torch.zeros(len(q), 3, 3, dtype=q.dtype)
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    skew = skew - skew.transpose(1, 2)
    eye3 = torch.eye(3, dtype=q.dtype)
    rot = (w * w - (v * v).sum(-1))[:, None, None] * eye3 + 2 * v[:, :, None] * v[:, None, :] + 2 * w[:, None, None] * skew
    cov = rot @ torch.diag_embed(scene["scales"] ** 2) @ rot.transpose(1, 2)
    rv, tv = scene["viewmats"][:, :3, :3], scene["viewmats"][:, :3, 3]
    pc = (rv[:, None] @ scene["means"][None, :, :, None]).squeeze(-1) + tv[:, None]  # [C, N, 3]
    cov_c = rv[:, None] @ cov[None] @ rv[:, None].transpose(-1, -2)
    fx, fy = scene["Ks"][:, 0, 0, None], scene["Ks"][:, 1, 1, None]
    cx, cy = scene["Ks"][:, 0, 2, None], scene["Ks"][:, 1, 2, None]
    x, y, z = pc.unbind(-1)
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], -1)
    gx, gy = 0.3 * 0.5 * width / fx, 0.3 * 0.5 * height / fy
    tx = z * torch.clamp(x / z, min=-(cx / fx + gx), max=(width - cx) / fx + gx)
    ty = z * torch.clamp(y / z, min=-(cy / fy + gy), max=(height - cy) / fy + gy)
    zeros = torch.zeros_like(z)
    jac = torch.stack(
        [torch.stack([fx / z, zeros, -fx * tx / z**2], -1), torch.stack([zeros, fy / z, -fy * ty / z**2], -1)], -2
    )
    cov2d = jac @ cov_c @ jac.transpose(-1, -2) + LOW_PASS_EPS * torch.eye(2, dtype=z.dtype)
    det = torch.linalg.det(cov2d)
    b = 0.5 * (cov2d[..., 0, 0] + cov2d[..., 1, 1])
    with torch.no_grad():
        radius = torch.ceil(3.0 * torch.sqrt(b + torch.sqrt(torch.clamp(b * b - det, min=0.01))))
        inside = (means2d[..., 0] + radius > 0) & (means2d[..., 0] - radius < width)
        inside &= (means2d[..., 1] + radius > 0) & (means2d[..., 1] - radius < height)
        radius = torch.where((z >= 0.01) & (det > 0) & inside, radius, torch.zeros_like(radius))
    return means2d, torch.linalg.inv(cov2d), z, radius


def brute_render(scene: Dict[str, Tensor], width: int, height: int, tile: int = TILE_SIZE):
    """Every pixel against every Gaussian in depth order, gsplat's loop written out per Gaussian."""
    means2d, inv_cov, depth, radius = brute_project(scene, width, height)
    if means2d.requires_grad:
        means2d.retain_grad()
    n_cams, n = depth.shape
    feats = scene["features"].expand(n_cams, n, -1) if scene["features"].dim() == 2 else scene["features"]
    ys, xs = torch.meshgrid(torch.arange(height, dtype=depth.dtype), torch.arange(width, dtype=depth.dtype), indexing="ij")
    px, py = xs.reshape(-1) + 0.5, ys.reshape(-1) + 0.5
    tile_x, tile_y = torch.floor(px / tile), torch.floor(py / tile)
    renders, depths, alphas = [], [], []
    n_stopped = n_clamped = 0
    for c in range(n_cams):
        trans = torch.ones_like(px)
        done = torch.zeros_like(px, dtype=torch.bool)
        colour = torch.zeros(len(px), feats.shape[-1] + 1, dtype=depth.dtype)
        for i in torch.argsort(depth[c]).tolist():
            r = radius[c, i]
            if r <= 0:
                continue
            mx, my = means2d[c, i, 0], means2d[c, i, 1]
            in_tiles = (tile_x >= torch.floor((mx - r) / tile)) & (tile_x < torch.ceil((mx + r) / tile))
            in_tiles &= (tile_y >= torch.floor((my - r) / tile)) & (tile_y < torch.ceil((my + r) / tile))
            d = torch.stack([mx - px, my - py], -1)
            sigma = 0.5 * torch.einsum("pi,ij,pj->p", d, inv_cov[c, i], d)
            raw_alpha = scene["opacities"][i] * torch.exp(-sigma)
            alpha = torch.clamp(raw_alpha, max=ALPHA_MAX)
            use = in_tiles & (sigma >= 0) & (alpha >= ALPHA_MIN) & ~done
            n_clamped += int((use & (raw_alpha > ALPHA_MAX)).sum())
            finished = use & (trans * (1 - alpha) <= TRANSMITTANCE_MIN)
            done = done | finished
            use = use & ~finished
            a = torch.where(use, alpha, torch.zeros_like(alpha))
            colour = colour + (a * trans)[:, None] * torch.cat([feats[c, i], depth[c, i, None]])[None]
            trans = trans * (1 - a)
        n_stopped += int(done.sum())
        alpha_img = 1 - trans
        rgb = colour[:, :-1]
        if scene.get("backgrounds") is not None:
            rgb = rgb + trans[:, None] * scene["backgrounds"][c]
        renders.append(rgb.reshape(height, width, -1))
        depths.append((colour[:, -1] / alpha_img.clamp(min=1e-10)).reshape(height, width, 1))
        alphas.append(alpha_img.reshape(height, width, 1))
    return {
        "render": torch.stack(renders), "depth": torch.stack(depths), "alpha": torch.stack(alphas),
        "means2d": means2d, "radius": radius, "n_stopped": n_stopped, "n_clamped": n_clamped,
    }


# ----------------------------------------------------------------------------- helpers
def leafs(scene: Dict[str, Tensor], dtype: torch.dtype) -> Dict[str, Tensor]:
    out = {k: v.detach().to(dtype).clone() for k, v in scene.items()}
    for name in PARAM_NAMES:
        out[name].requires_grad_(True)
    return out


def run_torch(scene: Dict[str, Tensor], width: int = WIDTH, height: int = HEIGHT):
    return rasterize_torch(
        scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["features"],
        scene["viewmats"], scene["Ks"], width, height, backgrounds=scene.get("backgrounds"),
    )


def loss_weights(shape: Tuple[int, ...], seed: int) -> Tensor:
    return torch.randn(shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def relative_error(a: Tensor, b: Tensor) -> float:
    return float((a.double() - b.double()).norm() / b.double().norm().clamp(min=1e-12))


# ----------------------------------------------------------------------------- tests
@pytest.mark.parametrize("seed", [0, 1])
def test_forward_matches_brute_force(seed: int) -> None:
    scene = make_scene(40, n_cams=2, seed=seed)
    scene["backgrounds"] = torch.rand(2, 4, dtype=torch.float64)
    ref = brute_render(scene, WIDTH, HEIGHT)
    ref_render, ref_depth, ref_alpha, ref_radius = ref["render"], ref["depth"], ref["alpha"], ref["radius"]
    out = run_torch({k: v.float() for k, v in scene.items()})
    assert out.render.shape == (2, HEIGHT, WIDTH, 4) and out.alpha.shape == (2, HEIGHT, WIDTH, 1)
    assert torch.equal(out.radii.long(), ref_radius.long())
    assert torch.equal(out.visible, ref_radius > 0)
    assert ref["n_stopped"] > 0, "the scene must hit the transmittance cut-off"
    assert ref["n_clamped"] > 0, "the scene must hit the alpha clamp"
    torch.testing.assert_close(out.render.double(), ref_render, atol=1e-5, rtol=0)
    torch.testing.assert_close(out.alpha.double(), ref_alpha, atol=1e-5, rtol=0)
    covered = ref_alpha > 0.05  # expected depth is ill-conditioned where almost nothing is seen
    torch.testing.assert_close(out.depth.double()[covered], ref_depth[covered], atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("dtype,tolerance", [(torch.float64, 1e-9), (torch.float32, 1e-3)])
def test_gradients_match_brute_force(dtype: torch.dtype, tolerance: float) -> None:
    scene = make_scene(30, n_cams=2, seed=3)
    scene["features"] = torch.rand(2, 30, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    scene["backgrounds"] = torch.rand(2, 3, dtype=torch.float64)
    w_render = loss_weights((2, HEIGHT, WIDTH, 3), 5)
    w_depth, w_alpha = loss_weights((2, HEIGHT, WIDTH, 1), 6), loss_weights((2, HEIGHT, WIDTH, 1), 7)

    ref = leafs(scene, torch.float64)
    r = brute_render(ref, WIDTH, HEIGHT)
    r_render, r_depth, r_alpha, r_means2d = r["render"], r["depth"], r["alpha"], r["means2d"]
    assert r["n_stopped"] > 0 and r["n_clamped"] > 0
    ((r_render * w_render).sum() + (r_depth * w_depth).sum() + (r_alpha * w_alpha).sum()).backward()

    ours = leafs(scene, dtype)
    out = run_torch(ours)
    ((out.render * w_render.to(dtype)).sum() + (out.depth * w_depth.to(dtype)).sum() + (out.alpha * w_alpha.to(dtype)).sum()).backward()

    for name in PARAM_NAMES:
        assert ref[name].grad.abs().sum() > 0, f"reference gradient of {name} is zero"
        err = relative_error(ours[name].grad, ref[name].grad)
        assert err < tolerance, f"{name}: relative gradient error {err:.2e}"
    visible = out.visible
    err = relative_error(out.means2d.grad[visible], r_means2d.grad[visible])
    assert err < tolerance, f"means2d.grad: relative error {err:.2e}"
    assert torch.all(out.means2d.grad[~visible] == 0)


def test_gradcheck_tiny() -> None:
    scene = make_scene(5, n_cams=1, seed=11, channels=2, walls=False)
    scene["means"][:, 2] = torch.linspace(-0.3, 0.3, 5, dtype=torch.float64)  # distinct depths
    names = list(PARAM_NAMES)
    inputs = tuple(scene[k].clone().requires_grad_(True) for k in names)

    def fn(*args: Tensor):
        s = dict(zip(names, args), Ks=scene["Ks"])
        out = run_torch(s, width=11, height=10)
        return out.render, out.alpha, out.depth

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_binning_lists_every_touched_tile_in_depth_order() -> None:
    scene = {k: v.float() for k, v in make_scene(60, n_cams=2, seed=2).items()}
    width, height = 45, 30
    proj = project_gaussians(scene["means"], scene["quats"], scene["scales"], scene["viewmats"], scene["Ks"], width, height)
    bins = bin_gaussians(proj.means2d, proj.radii, proj.depths, width, height)
    n = scene["means"].shape[0]
    n_tiles = bins.tiles_x * bins.tiles_y
    expected = set()
    for c in range(2):
        for i in range(n):
            r = int(proj.radii[c, i])
            if r == 0:
                continue
            mx, my = proj.means2d[c, i].tolist()
            for ty in range(max(0, math.floor((my - r) / TILE_SIZE)), min(bins.tiles_y, math.ceil((my + r) / TILE_SIZE))):
                for tx in range(max(0, math.floor((mx - r) / TILE_SIZE)), min(bins.tiles_x, math.ceil((mx + r) / TILE_SIZE))):
                    expected.add((c * n_tiles + ty * bins.tiles_x + tx, c * n + i))
    got = set()
    for t in range(2 * n_tiles):
        start, count = int(bins.tile_starts[t]), int(bins.tile_counts[t])
        ids = bins.flat_ids[start : start + count]
        depths = proj.depths.reshape(-1)[ids]
        assert torch.all(depths[1:] >= depths[:-1]), f"tile {t} is not depth sorted"
        got.update((t, int(i)) for i in ids)
    assert got == expected and len(bins.flat_ids) == len(expected)


def test_culled_gaussians_get_zero_radius_and_finite_zero_gradients() -> None:
    scene = leafs(make_scene(6, n_cams=1, seed=5, walls=False), torch.float32)
    with torch.no_grad():
        scene["means"][0] = torch.tensor([0.0, 0.0, -10.0])  # behind the camera (camera at z = -3)
        scene["means"][1] = torch.tensor([40.0, 0.0, 0.0])  # far off screen
    out = run_torch(scene)
    assert out.radii[0, 0] == 0 and out.radii[0, 1] == 0
    (out.render.sum() + out.depth.sum()).backward()
    for name in PARAM_NAMES:
        assert torch.isfinite(scene[name].grad).all(), name
    assert torch.all(scene["means"].grad[:2] == 0) and torch.all(scene["opacities"].grad[:2] == 0)


def test_empty_view_renders_the_background() -> None:
    scene = leafs(make_scene(4, n_cams=1, seed=6, walls=False), torch.float32)
    with torch.no_grad():
        scene["means"][:, 2] = -20.0  # all behind the camera
    background = torch.tensor([[0.2, 0.4, 0.6, 0.0]])
    out = rasterize_torch(
        scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["features"],
        scene["viewmats"], scene["Ks"], WIDTH, HEIGHT, backgrounds=background,
    )
    assert torch.allclose(out.render, background[:, None, None, :].expand_as(out.render))
    assert torch.all(out.alpha == 0) and torch.all(out.depth == 0) and not out.visible.any()


@pytest.mark.parametrize(
    "name,bad",
    [
        ("means", lambda s: s["means"][:, :2]),
        ("quats", lambda s: s["quats"][:-1]),
        ("scales", lambda s: s["scales"][None]),
        ("opacities", lambda s: s["opacities"][:, None]),
        ("features", lambda s: s["features"][:-1]),
        ("viewmats", lambda s: s["viewmats"][:, :3]),
        ("Ks", lambda s: s["Ks"][:, :2]),
        ("backgrounds", lambda s: torch.zeros(1, 7)),
    ],
)
def test_shape_errors_name_the_argument(name: str, bad) -> None:
    scene = {k: v.float() for k, v in make_scene(5, n_cams=1, seed=0, walls=False).items()}
    scene["backgrounds"] = torch.zeros(1, 4)
    scene[name] = bad(scene)
    with pytest.raises(ValueError, match=name):
        run_torch(scene)


def test_projection_matches_gsplat_torch_reference() -> None:
    torch_impl = pytest.importorskip("gsplat.cuda._torch_impl")
    scene = {k: v.float() for k, v in make_scene(50, n_cams=2, seed=9).items()}
    proj = project_gaussians(scene["means"], scene["quats"], scene["scales"], scene["viewmats"], scene["Ks"], WIDTH, HEIGHT)
    covars, _ = torch_impl._quat_scale_to_covar_preci(scene["quats"], scene["scales"], triu=False)
    radii, means2d, depths, conics, _ = torch_impl._fully_fused_projection(
        scene["means"], covars, scene["viewmats"], scene["Ks"], WIDTH, HEIGHT, eps2d=LOW_PASS_EPS
    )
    vis = radii > 0
    assert torch.equal(proj.radii, radii)
    torch.testing.assert_close(proj.means2d[vis], means2d[vis], atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(proj.conics[vis], conics[vis], atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(proj.depths[vis], depths[vis])


def test_select_backend_on_cpu() -> None:
    from edygs_ns.render.cpu_backend import compiled_available, rasterize_cpu

    expected = rasterize_cpu if compiled_available() else rasterize_torch  # the compiled one when it builds
    assert select_backend(torch.device("cpu")) is expected
    assert select_backend(torch.device("cpu"), "torch") is rasterize_torch
    with pytest.raises(ValueError, match="unknown rasterizer"):
        select_backend(torch.device("cpu"), "opengl")


def test_block_size_saving_and_grad_mode_do_not_change_results(monkeypatch: pytest.MonkeyPatch) -> None:
    scene = make_scene(40, n_cams=2, seed=8)
    weights = loss_weights((2, HEIGHT, WIDTH, 4), 9)

    def run() -> Dict[str, Tensor]:
        leaves = leafs(scene, torch.float64)
        out = run_torch(leaves)
        ((out.render * weights).sum() + out.depth.sum() + out.alpha.sum()).backward()
        return {"render": out.render.detach(), **{k: leaves[k].grad for k in PARAM_NAMES}}

    reference = run()
    monkeypatch.setattr(torch_backend, "BLOCK_ELEMENTS", 256)  # one tile per block
    monkeypatch.setattr(torch_backend, "SAVE_BUDGET_BYTES", 0)  # backward recomputes alpha
    other = run()
    for key, value in reference.items():
        torch.testing.assert_close(other[key], value, rtol=1e-10, atol=1e-12, msg=key)
    with torch.no_grad():
        inference = run_torch(scene)
    torch.testing.assert_close(inference.render, reference["render"], rtol=1e-12, atol=1e-12)


def test_alpha_cut_culling_keeps_the_image(monkeypatch: pytest.MonkeyPatch) -> None:
    """Dropping tiles outside the alpha >= 1/255 box changes nothing but the work."""
    scene = {k: v.float() for k, v in make_scene(60, n_cams=1, seed=10).items()}
    proj = project_gaussians(scene["means"], scene["quats"], scene["scales"], scene["viewmats"], scene["Ks"], WIDTH, HEIGHT)
    square = bin_gaussians(proj.means2d, proj.radii, proj.depths, WIDTH, HEIGHT)
    tight = bin_gaussians(proj.means2d, proj.radii, proj.depths, WIDTH, HEIGHT, TILE_SIZE, proj.conics, scene["opacities"])
    assert len(tight.flat_ids) < len(square.flat_ids)
    culled = run_torch(scene)
    monkeypatch.setattr(torch_backend, "bin_gaussians", lambda *args: bin_gaussians(*args[:6]))
    full = run_torch(scene)
    torch.testing.assert_close(culled.render, full.render, atol=1e-6, rtol=0)


@pytest.mark.parametrize("n_cams", [1, 2])
def test_projection_backward_matches_autograd(n_cams: int) -> None:
    """The hand-written projection backward against autograd through the same equations."""
    scene = make_scene(50, n_cams=n_cams, seed=12)
    with torch.no_grad():  # one Gaussian behind the first camera, one far outside its view
        scene["means"][5] = torch.tensor([0.0, 0.0, -10.0], dtype=torch.float64)
        scene["means"][6] = torch.tensor([30.0, 0.0, 0.0], dtype=torch.float64)
    names = ("means", "quats", "scales", "viewmats")
    g = torch.Generator().manual_seed(13)
    w2, w3, wz = (torch.randn(n_cams, 50, k, generator=g, dtype=torch.float64) for k in (2, 3, 1))
    grads = []
    for project in (project_gaussians, project_gaussians_autograd):
        leaves = {k: scene[k].clone().requires_grad_(True) for k in names}
        proj = project(leaves["means"], leaves["quats"], leaves["scales"], leaves["viewmats"], scene["Ks"], WIDTH, HEIGHT)
        ((proj.means2d * w2).sum() + (proj.conics * w3).sum() + (proj.depths * wz[..., 0]).sum()).backward()
        grads.append({k: leaves[k].grad for k in names})
        grads[-1]["radii"] = proj.radii
    assert torch.equal(grads[0].pop("radii"), grads[1].pop("radii"))
    for name in names:
        err = relative_error(grads[0][name], grads[1][name])
        assert err < 1e-12, f"{name}: relative error {err:.2e}"


def test_intrinsics_gradients_fall_back_to_autograd() -> None:
    scene = leafs(make_scene(20, n_cams=1, seed=14, walls=False), torch.float64)
    scene["Ks"].requires_grad_(True)
    out = run_torch(scene)
    (out.render.sum() + out.depth.sum()).backward()
    assert scene["Ks"].grad is not None and scene["Ks"].grad.abs().sum() > 0
    assert scene["means"].grad.abs().sum() > 0


@pytest.mark.parametrize("tile", [16, 7])
def test_other_tile_sizes_match_brute_force(tile: int) -> None:
    """Even tiles composite on quadrant cells, odd ones on whole tiles; both keep the tile rule."""
    scene = make_scene(40, n_cams=1, seed=15)
    ref = brute_render(scene, WIDTH, HEIGHT, tile=tile)
    s = {k: v.float() for k, v in scene.items()}
    out = rasterize_torch(
        s["means"], s["quats"], s["scales"], s["opacities"], s["features"], s["viewmats"], s["Ks"], WIDTH, HEIGHT,
        tile_size=tile,
    )
    torch.testing.assert_close(out.render.double(), ref["render"], atol=1e-5, rtol=0)
    torch.testing.assert_close(out.alpha.double(), ref["alpha"], atol=1e-5, rtol=0)


def test_outputs_are_freed_without_the_garbage_collector() -> None:
    """No reference cycle through the custom autograd Functions (it leaked a graph per call)."""
    scene = leafs(make_scene(20, n_cams=1, seed=16, walls=False), torch.float32)
    out = run_torch(scene)
    refs = [weakref.ref(out.means2d), weakref.ref(out.render)]
    del out
    assert all(r() is None for r in refs)


def test_reused_buffers_do_not_change_results() -> None:
    """The per-thread spare buffers: other scenes, dropped graphs and no-grad calls in between."""
    scene_a = leafs(make_scene(40, n_cams=2, seed=17), torch.float32)
    scene_b = leafs(make_scene(25, n_cams=1, seed=18), torch.float32)

    def run(scene: Dict[str, Tensor]) -> Dict[str, Tensor]:
        out = run_torch(scene)
        (out.render.sum() + out.depth.sum() + out.alpha.sum()).backward()
        grads = {k: scene[k].grad.clone() for k in PARAM_NAMES}
        for k in PARAM_NAMES:
            scene[k].grad = None
        return {"render": out.render.detach(), **grads}

    first = run(scene_a)
    run(scene_b)
    run_torch(scene_b)  # graph dropped without backward
    with torch.no_grad():
        run_torch(scene_b)
    again = run(scene_a)
    for key, value in first.items():
        assert torch.equal(again[key], value), key


def test_cell_culling_keeps_image_and_gradients(monkeypatch: pytest.MonkeyPatch) -> None:
    """Small, elongated, rotated Gaussians: dropping the tile quadrants their alpha >= 1/255
    ellipse misses changes neither the image nor the gradients (float64)."""
    g = torch.Generator().manual_seed(19)
    n, width, height = 300, 64, 48
    dt = torch.float64
    scene = {
        "means": torch.cat([(torch.rand(n, 2, generator=g, dtype=dt) - 0.5) * torch.tensor([2.6, 2.0], dtype=dt),
                            torch.rand(n, 1, generator=g, dtype=dt) - 0.5], 1),
        "quats": torch.randn(n, 4, generator=g, dtype=dt),
        "scales": torch.rand(n, 3, generator=g, dtype=dt) * torch.tensor([0.12, 0.02, 0.02], dtype=dt) + 0.004,
        "opacities": 0.05 + 0.9 * torch.rand(n, generator=g, dtype=dt),
        "features": torch.rand(n, 3, generator=g, dtype=dt),
        "viewmats": look_at_viewmat(torch.tensor([0.0, 0.0, -3.0], dtype=dt), torch.zeros(3, dtype=dt))[None],
        "Ks": torch.tensor([[[60.0, 0.0, width / 2], [0.0, 60.0, height / 2], [0.0, 0.0, 1.0]]], dtype=dt),
    }
    weights = loss_weights((1, height, width, 3), 20)

    def run() -> Dict[str, Tensor]:
        leaves = leafs(scene, dt)
        out = rasterize_torch(
            leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["features"],
            leaves["viewmats"], leaves["Ks"], width, height,
        )
        ((out.render * weights).sum() + out.alpha.sum()).backward()
        return {"render": out.render.detach(), **{k: leaves[k].grad for k in PARAM_NAMES}}

    culled = run()
    proj = project_gaussians(scene["means"], scene["quats"], scene["scales"], scene["viewmats"], scene["Ks"], width, height)
    bins = bin_gaussians(proj.means2d, proj.radii, proj.depths, width, height, TILE_SIZE, proj.conics, scene["opacities"])
    full_bins = bin_gaussians(proj.means2d, proj.radii, proj.depths, width, height)
    reached = torch.stack([(bins.quadrants >> q) & 1 for q in range(4)]).sum()
    assert reached < 0.8 * 4 * len(full_bins.flat_ids), "the scene must exercise the quadrant cut"
    monkeypatch.setattr(torch_backend, "bin_gaussians", lambda *args: bin_gaussians(*args[:6]))
    full = run()
    for key, value in full.items():
        torch.testing.assert_close(culled[key], value, rtol=1e-9, atol=1e-12, msg=key)


@pytest.mark.parametrize("slot_pixels", [0, 10**6])
def test_whole_tiles_and_quadrant_cells_agree(monkeypatch: pytest.MonkeyPatch, slot_pixels: int) -> None:
    """Compositing a tile whole or per quadrant is the same computation (float64)."""
    scene = make_scene(40, n_cams=2, seed=21)
    weights = loss_weights((2, HEIGHT, WIDTH, 4), 22)

    def run() -> Dict[str, Tensor]:
        leaves = leafs(scene, torch.float64)
        out = run_torch(leaves)
        ((out.render * weights).sum() + out.depth.sum() + out.alpha.sum()).backward()
        return {"render": out.render.detach(), **{k: leaves[k].grad for k in PARAM_NAMES}}

    calls = []
    split = torch_backend._split_cells
    monkeypatch.setattr(torch_backend, "_split_cells", lambda *a: calls.append(split(*a)) or calls[-1])
    reference = run()
    assert (calls[0].tile_counts > 0).any() and (calls[0].counts > 0).any(), "the default must mix both"
    monkeypatch.setattr(torch_backend, "SLOT_PIXELS", slot_pixels)
    other = run()
    whole, split_cells = (calls[1].tile_counts > 0).any(), (calls[1].counts > 0).any()
    assert (split_cells and not whole) if slot_pixels == 0 else (whole and not split_cells)
    for key, value in reference.items():
        torch.testing.assert_close(other[key], value, rtol=1e-10, atol=1e-12, msg=key)
