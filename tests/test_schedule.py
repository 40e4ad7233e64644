"""The phase switch: which phase each step is in, what trains, which losses count."""

import pytest

from edygs_ns.model.ablations import ABLATIONS, apply_ablation
from edygs_ns.model.edygs_model import EdygsModelConfig
from edygs_ns.model.phases import (
    CAMERA_GROUP, DEFORMATION_GROUP, MASK_GROUP, Phase, PhaseSchedule, is_active, is_trainable, phase_at,
)


def test_phase_boundaries():
    s = PhaseSchedule(pose_init_iters=10, static_iters=20)
    assert [phase_at(i, s) for i in (0, 9, 10, 29, 30, 10_000)] == [
        Phase.POSE_INIT, Phase.POSE_INIT, Phase.STATIC, Phase.STATIC, Phase.DYNAMIC, Phase.DYNAMIC,
    ]
    assert phase_at(0, PhaseSchedule(0, 0)) is Phase.DYNAMIC


def test_what_trains_when():
    assert not is_trainable(CAMERA_GROUP, Phase.POSE_INIT)
    assert not is_trainable(MASK_GROUP, Phase.POSE_INIT)
    assert is_trainable(MASK_GROUP, Phase.STATIC) and is_trainable(CAMERA_GROUP, Phase.STATIC)
    assert not is_trainable(DEFORMATION_GROUP, Phase.STATIC)
    assert all(is_trainable(g, Phase.DYNAMIC) for g in (MASK_GROUP, CAMERA_GROUP, DEFORMATION_GROUP, "means"))


def test_which_losses_count_when():
    assert is_active("edi", Phase.POSE_INIT) and not is_active("event", Phase.POSE_INIT)
    assert is_active("edi_static", Phase.STATIC) and is_active("mask_l1", Phase.STATIC)
    assert not is_active("motion", Phase.STATIC)
    assert is_active("motion", Phase.DYNAMIC) and is_active("mask_consistency", Phase.DYNAMIC)
    assert not is_active("edi_static", Phase.DYNAMIC) and not is_active("mask_l1", Phase.DYNAMIC)
    assert not is_active("blur", Phase.POSE_INIT) and is_active("blur", Phase.STATIC) and is_active("blur", Phase.DYNAMIC)


def test_ablation_presets_set_switches_and_skip_warmup_without_edi():
    for name, switches in ABLATIONS.items():
        cfg = EdygsModelConfig(ablation=name)  # type: ignore[arg-type]
        assert {k: getattr(cfg, k) for k in switches} == switches
    cfg = EdygsModelConfig(schedule=PhaseSchedule(5, 7), ablation="events-only")
    assert (cfg.schedule.pose_init_iters, cfg.schedule.static_iters) == (0, 12)
    apply_ablation(cfg)  # idempotent
    assert (cfg.schedule.pose_init_iters, cfg.schedule.static_iters) == (0, 12)
    assert EdygsModelConfig(ablation="full").use_blur_loss and not EdygsModelConfig(ablation="paper").use_blur_loss
    paper = {k: v for k, v in ABLATIONS["paper"].items() if k != "use_blur_loss"}
    assert paper == {k: v for k, v in ABLATIONS["full"].items() if k != "use_blur_loss"}
    plain = EdygsModelConfig(use_event_loss=False)
    assert plain.use_event_loss is False and plain.ablation is None


def test_a_misspelt_loss_name_raises() -> None:
    from edygs_ns.losses.names import LossName
    from edygs_ns.model.phases import is_active

    assert is_active(LossName.EVENT, Phase.STATIC) and is_active("event", Phase.STATIC)
    with pytest.raises(ValueError, match="evnt"):
        is_active("evnt", Phase.STATIC)


def test_every_loss_name_the_model_uses_is_a_loss_term() -> None:
    """The model asks is_active(...) with LossName members, and its loss-dict keys are their values."""
    import ast
    from pathlib import Path

    import edygs_ns.model.edygs_model as model_module
    from edygs_ns.losses.names import LossName

    tree = ast.parse(Path(model_module.__file__).read_text(encoding="utf-8"))
    calls = [node.args[0] for node in ast.walk(tree) if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "is_active"]
    assert calls and all(isinstance(a, ast.Attribute) and getattr(a.value, "id", None) == "LossName" for a in calls)
    asked = {LossName[a.attr].value for a in calls}  # an unknown member would raise KeyError here
    keyed = {node.slice.value for node in ast.walk(tree) if isinstance(node, ast.Subscript)
             and getattr(node.value, "id", None) == "losses" and isinstance(getattr(node.slice, "value", None), str)}
    names = {name.value for name in LossName}
    assert asked and asked <= names, asked - names
    assert keyed - {"none"} == asked


def test_parameter_groups_come_from_the_gaussian_attributes() -> None:
    from edygs_ns.configs.method_configs import LEARNING_RATES, PARAMETER_GROUPS, optimizer_configs
    from edygs_ns.model.gaussians import GAUSSIAN_ATTRIBUTES
    from edygs_ns.model.phases import GAUSSIAN_GROUPS, MASK_GROUP, TRAINABLE

    assert PARAMETER_GROUPS[: len(GAUSSIAN_ATTRIBUTES)] == GAUSSIAN_ATTRIBUTES
    assert set(optimizer_configs()) == set(PARAMETER_GROUPS) == set(LEARNING_RATES)
    assert GAUSSIAN_GROUPS | {MASK_GROUP} == set(GAUSSIAN_ATTRIBUTES)
    assert set().union(*TRAINABLE.values()) == set(PARAMETER_GROUPS)
