"""The deformation field starts as the identity and can learn an offset."""

import torch

from edygs_ns.model.deformation import DeformationConfig, DeformationField, positional_encoding

SMALL = DeformationConfig(depth=4, width=32, skip_layer=2, xyz_frequencies=4, time_frequencies=3)


def test_positional_encoding_shape_and_identity_part():
    x = torch.rand(5, 3)
    enc = positional_encoding(x, 10)
    assert enc.shape == (5, 63)
    assert torch.equal(enc[:, :3], x)


def test_field_is_identity_at_init_and_stops_gradient_into_means():
    torch.manual_seed(0)
    field = DeformationField(DeformationConfig())
    means = torch.rand(7, 3, requires_grad=True)
    d_xyz, d_rot, d_scale = field(means, 0.3)
    assert d_xyz.shape == (7, 3) and d_rot.shape == (7, 4) and d_scale.shape == (7, 3)
    assert torch.count_nonzero(d_xyz) == 0 and torch.count_nonzero(d_rot) == 0 and torch.count_nonzero(d_scale) == 0
    (d_xyz.sum() + d_rot.sum()).backward()
    assert means.grad is None


def test_field_learns_a_time_dependent_offset():
    torch.manual_seed(0)
    field = DeformationField(SMALL)
    opt = torch.optim.Adam(field.parameters(), lr=3e-3)
    means = torch.rand(32, 3)
    times = [0.0, 0.5, 1.0]

    def error() -> float:
        with torch.no_grad():
            return sum(((field(means, t)[0] - torch.tensor([t, 0.0, 0.0])) ** 2).mean().item() for t in times)

    before = error()
    for _ in range(300):
        opt.zero_grad()
        loss = sum(((field(means, t)[0] - torch.tensor([t, 0.0, 0.0])) ** 2).mean() for t in times)
        loss.backward()
        opt.step()
    assert error() < 0.05 * before


def test_colour_head_starts_at_zero_and_is_absent_when_off():
    from dataclasses import replace

    means = torch.rand(6, 3)
    assert DeformationField(SMALL).offsets(means, 0.2)[3] is None
    colour = DeformationField(replace(SMALL, colour=True)).offsets(means, 0.2)[3]
    assert colour.shape == (6, 3) and torch.count_nonzero(colour) == 0


def test_a_checkpoint_without_the_colour_head_loads_with_a_zero_head():
    from dataclasses import replace

    torch.manual_seed(0)
    old = DeformationField(SMALL)
    state = old.state_dict()
    new = DeformationField(replace(SMALL, colour=True))
    with torch.no_grad():
        new.head_colour.weight.fill_(1.0)  # so that loading must set it
    new.prepare_load(state, "")
    new.load_state_dict(state)
    means = torch.rand(5, 3)
    for a, b in zip(old.offsets(means, 0.7)[:3], new.offsets(means, 0.7)[:3]):
        assert torch.equal(a, b)
    assert torch.count_nonzero(new.offsets(means, 0.7)[3]) == 0
