"""The render cache that completes an exposure for the blur loss."""

import pytest
import torch

from edygs_ns.model.exposure_cache import ExposureCache

H, W = 3, 4


def _cache() -> ExposureCache:
    # exposures 0 and 1 with 3 latents each, then a camera of no exposure
    cache = ExposureCache(torch.tensor([0, 0, 0, 1, 1, 1, -1]))
    cache.fill(lambda i: torch.full((H, W, 3), float(i)))
    return cache


def test_complete_puts_live_renders_in_their_places_and_the_rest_from_the_cache():
    cache = _cache()
    live = torch.full((2, H, W, 3), 10.0, requires_grad=True)
    (stack,) = cache.complete(torch.tensor([4, 5]), live).values()
    assert stack.shape == (3, H, W, 3)
    assert stack[:, 0, 0, 0].tolist() == [3.0, 10.0, 10.0]
    stack.sum().backward()
    assert torch.equal(live.grad, torch.ones_like(live))  # gradients reach the live renders only
    assert cache.exposures(torch.tensor([4, 5, 6])) == [1]


def test_store_replaces_the_cached_render_and_state_round_trips():
    cache = _cache()
    cache.store(torch.tensor([0, 1]), torch.full((2, H, W, 3), 7.0))
    (stack,) = cache.complete(torch.tensor([2]), torch.zeros(1, H, W, 3)).values()
    assert stack[:, 0, 0, 0].tolist() == [7.0, 7.0, 0.0]
    fresh = ExposureCache(torch.tensor([0, 0, 0, 1, 1, 1, -1]))
    assert not fresh.filled
    state = cache.state_dict()
    fresh.prepare_load(state, "")
    fresh.load_state_dict(state)
    assert fresh.filled and torch.equal(fresh.renders, cache.renders)
    old = ExposureCache(torch.tensor([0, 0]))
    legacy: dict = {}
    old.prepare_load(legacy, "cache.")  # a checkpoint without the cache loads as an empty one
    assert set(legacy) == {"cache.renders"} and not old.filled


def test_complete_refuses_an_empty_cache():
    with pytest.raises(RuntimeError, match="fill"):
        ExposureCache(torch.tensor([0, 0])).complete(torch.tensor([0]), torch.zeros(1, H, W, 3))
