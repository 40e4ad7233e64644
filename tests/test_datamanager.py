"""The EDyGS datamanager on a tiny processed scene, on the CPU."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
import torch
from PIL import Image
from scene_fixtures import write_processed_scene

from edygs_ns.data.datamanager import EdygsDataManager, EdygsDataManagerConfig
from edygs_ns.data.dataparser import EdygsDataParserConfig


def _manager(root, **dataparser_kwargs) -> EdygsDataManager:
    config = EdygsDataManagerConfig(dataparser=EdygsDataParserConfig(data=root, **dataparser_kwargs))
    return config.setup(device="cpu", test_mode="val")


def _pixels(path) -> torch.Tensor:
    return torch.from_numpy(np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0)


@pytest.fixture
def scene(tmp_path):
    return write_processed_scene(tmp_path / "scene", n_blurry=3, k=4, n_novel=2)


def test_pairs_are_consecutive_latents_with_their_events(scene):
    dm = _manager(scene.root)
    assert dm.includes_time and dm.config.cache_images == "cpu"
    assert len(dm.pairs) == scene.n_blurry * (scene.k - 1)
    for step in range(len(dm.pairs)):
        cameras, batch = dm.next_train(step)
        assert cameras.shape == (2,)
        i, j = batch["image_idx"].tolist()
        b, lat = divmod(i, scene.k)
        assert j == i + 1 and j // scene.k == b  # same exposure, next latent
        assert cameras.metadata["cam_idx"].flatten().tolist() == [i, j]
        assert cameras.times[0, 0] < cameras.times[1, 0]
        assert batch["image"].shape == (2, scene.height, scene.width, 3) and batch["image"].dtype == torch.float32
        assert torch.allclose(batch["image"][1], _pixels(scene.root / f"latents/{b:04d}_{lat + 1}.png"))
        assert batch["event_map"].shape == (scene.height, scene.width)
        assert torch.equal(batch["event_map"], torch.from_numpy(scene.event_maps[b, lat]))
        assert batch["blurry"].shape == (1, scene.height, scene.width, 3)
        assert torch.allclose(batch["blurry"][0], _pixels(scene.blurry_files[b]))


def test_every_pair_once_per_epoch(scene):
    dm = _manager(scene.root)
    n = len(dm.pairs)
    for _ in range(2):
        served = Counter(tuple(dm.next_train(0)[1]["image_idx"].tolist()) for _ in range(n))
        assert set(served) == set(dm.pairs) and set(served.values()) == {1}


def test_single_cameras_without_pairing(scene):
    config = EdygsDataManagerConfig(dataparser=EdygsDataParserConfig(data=scene.root), pair_events=False)
    dm = config.setup(device="cpu")
    seen = set()
    for step in range(scene.n_blurry * scene.k):
        cameras, batch = dm.next_train(step)
        assert cameras.shape == (1,) and batch["image"].shape == (1, scene.height, scene.width, 3)
        assert "event_map" not in batch
        seen.add(int(batch["image_idx"][0]))
    assert seen == set(range(scene.n_blurry * scene.k))


def test_blurry_baseline_serves_blurry_frames(scene):
    dm = _manager(scene.root, image_source="blurry")
    cameras, batch = dm.next_train(0)
    assert cameras.shape == (1,) and not dm.serves_pairs
    b = int(batch["image_idx"][0])
    assert torch.allclose(batch["image"][0], _pixels(scene.blurry_files[b]))


def test_eval_returns_novel_view_with_time_and_mask(scene):
    dm = _manager(scene.root)
    times = set()
    for step in range(2):
        camera, batch = dm.next_eval(step)
        idx = batch["image_idx"]
        assert camera.shape == (1,) and batch["image"].shape == (scene.height, scene.width, 3)
        assert torch.allclose(batch["image"], _pixels(scene.novel_files[idx]))
        assert float(camera.times[0, 0]) == pytest.approx(scene.novel_times[idx], abs=1e-6)
        mask = batch["motion_mask"]
        assert mask.shape == (scene.height, scene.width, 1) and set(mask.unique().tolist()) <= {0.0, 1.0}
        times.add(round(float(camera.times[0, 0]), 6))
    assert len(times) == 2
    assert len(dm.fixed_indices_eval_dataloader) == 2
    assert "motion_mask" in dm.fixed_indices_eval_dataloader[0][1]


def test_points_exposed_for_seeding(scene):
    dm = _manager(scene.root)
    xyz = dm.train_dataparser_outputs.metadata["points3D_xyz"]
    assert xyz.shape == (len(scene.points), 3)
    assert "event_maps" not in dm.train_dataset.metadata  # not deep-copied into the dataset
    assert dm.event_maps is not None and dm.event_maps.shape == scene.event_maps.shape


def test_time_window_limits_the_pairs_served(scene):
    dm = _manager(scene.root)
    times = dm.train_cameras.times.reshape(-1)
    lo, hi = float(times.min()), float(times.median())
    dm.set_time_window((lo, hi))
    inside = {p for p in dm.pairs if lo <= times[p[0]] <= hi and lo <= times[p[1]] <= hi}
    assert 0 < len(inside) < len(dm.pairs)
    served = {tuple(dm.next_train(0)[1]["image_idx"].tolist()) for _ in range(3 * len(dm.pairs))}
    assert served == inside
    dm.set_time_window((5.0, 6.0))  # no pair inside: the pair nearest the window is served
    assert tuple(dm.next_train(0)[1]["image_idx"].tolist()) == max(dm.pairs, key=lambda p: float(times[p[0]]))
    dm.set_time_window(None)
    served = {tuple(dm.next_train(0)[1]["image_idx"].tolist()) for _ in range(3 * len(dm.pairs))}
    assert served == set(dm.pairs)


def test_blurry_frame_of_the_wrong_size_is_named(scene):
    Image.new("RGB", (scene.width + 1, scene.height)).save(scene.blurry_files[1])
    with pytest.raises(ValueError, match=str(scene.blurry_files[1].name)):
        _manager(scene.root)


def test_truncated_latent_png_names_the_file(scene):
    latent = sorted((scene.root / "latents").glob("*.png"))[2]
    latent.write_bytes(latent.read_bytes()[:60])
    manager = _manager(scene.root)
    with pytest.raises(ValueError, match=rf"{latent.name}: cannot decode the image .*edygs-process"):
        manager.cached_train


def test_deleted_event_maps_are_named_not_called_a_raw_capture(scene):
    from edygs_ns.data.layouts import detect_layout

    (scene.root / "event_maps.npy").unlink()
    with pytest.raises(FileNotFoundError, match=r"event_maps\.npy: event maps of the processed scene .* missing"):
        detect_layout(scene.root)
    with pytest.raises(FileNotFoundError, match=r"event_maps\.npy: event maps"):
        _manager(scene.root)


def test_cuda_asked_without_a_gpu_fails_in_one_line(scene):
    if torch.cuda.is_available():
        pytest.skip("this machine has a CUDA GPU")
    config = EdygsDataManagerConfig(dataparser=EdygsDataParserConfig(data=scene.root))
    with pytest.raises(RuntimeError) as caught:
        config.setup(device="cuda:0", test_mode="val")
    message = str(caught.value)
    assert "\n" not in message and "cuda:0" in message and "ns-train edygs-cpu" in message and "--machine.device-type cpu" in message
