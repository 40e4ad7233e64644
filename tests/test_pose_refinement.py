"""Pose refinement with a slower rotation (edygs_ns/model/pose_refinement.py)."""

from __future__ import annotations

import pytest
import torch
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig

from edygs_ns.model.pose_refinement import ROTATION_SCALE_KEY, PoseRefinementConfig


def _angle(c2w: torch.Tensor) -> torch.Tensor:
    """[C] rotation angle (rad) of [C, 3, 4] correction matrices."""
    trace = c2w[:, 0, 0] + c2w[:, 1, 1] + c2w[:, 2, 2]
    return torch.arccos(((trace - 1.0) / 2.0).clamp(-1.0, 1.0))


def test_rotation_parameters_are_scaled_and_translations_are_not() -> None:
    refiner = PoseRefinementConfig(rotation_step=0.1).setup(num_cameras=3, device="cpu")
    with torch.no_grad():
        refiner.pose_adjustment[1] = torch.tensor([0.2, -0.1, 0.05, 0.0, 0.0, 0.5])
    out = refiner(torch.tensor([0, 1]))
    assert torch.allclose(out[0], torch.eye(4)[:3, :4])
    assert torch.allclose(out[1, :, 3], torch.tensor([0.2, -0.1, 0.05]))
    assert _angle(out[1:2]).item() == pytest.approx(0.05, abs=1e-5)
    assert torch.allclose(refiner.adjustment()[1, 3:], torch.tensor([0.0, 0.0, 0.05]))


def test_one_adam_step_turns_a_tenth_as_far_as_it_moves() -> None:
    refiner = PoseRefinementConfig(rotation_step=0.1).setup(num_cameras=1, device="cpu")
    optimiser = torch.optim.Adam(refiner.parameters(), lr=1e-3)
    out = refiner(torch.tensor([0]))
    # pull the camera along x and turn it about z: both parts get a gradient of the same sign
    loss = -(out[0, 0, 3] + out[0, 1, 0])
    loss.backward()
    optimiser.step()
    applied = refiner.adjustment().detach()[0]
    assert applied[0].item() == pytest.approx(1e-3, rel=1e-3)
    assert applied[5].item() == pytest.approx(1e-4, rel=1e-3)


def test_a_checkpoint_without_the_factor_loads_with_the_poses_it_trained() -> None:
    """Older runs stepped rotations like nerfstudio: their checkpoints load with a factor of 1."""
    legacy = CameraOptimizerConfig(mode="SO3xR3").setup(num_cameras=2, device="cpu")
    with torch.no_grad():
        legacy.pose_adjustment[0] = torch.tensor([0.01, 0.0, 0.0, 0.02, -0.03, 0.01])
    state = {k: v.clone() for k, v in legacy.state_dict().items()}
    assert ROTATION_SCALE_KEY not in state
    refiner = PoseRefinementConfig(rotation_step=0.1).setup(num_cameras=2, device="cpu")
    refiner.prepare_load(state, "")
    refiner.load_state_dict(state)
    index = torch.tensor([0, 1])
    assert torch.allclose(refiner(index), legacy(index), atol=1e-6)
    # a new checkpoint keeps its own factor
    fresh = PoseRefinementConfig(rotation_step=0.1).setup(num_cameras=2, device="cpu")
    state = fresh.state_dict()
    refiner.prepare_load(state, "")
    refiner.load_state_dict(state)
    assert refiner.rotation_scale.item() == pytest.approx(0.1)


def test_off_has_no_parameters_and_rejects_a_bad_factor() -> None:
    off = PoseRefinementConfig(mode="off").setup(num_cameras=4, device="cpu")
    assert list(off.parameters()) == []
    assert torch.allclose(off(torch.tensor([2, 3])), torch.eye(4)[:3, :4].expand(2, 3, 4))
    with pytest.raises(ValueError, match="rotation_step"):
        PoseRefinementConfig(rotation_step=0.0).setup(num_cameras=1, device="cpu")
