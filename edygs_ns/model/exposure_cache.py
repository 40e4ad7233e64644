"""The latest render of every training latent, to complete an exposure for the blur loss.

A training step renders two latents of one exposure; the blur loss needs all k. The other k − 2
come from this cache: each latent's render from the last step that drew it (no gradient), or its
training image (the EDI latent) until it was first drawn. The cache adds no render to a step.
The cache is a buffer of the model (float16, [N, H, W, 3] linear intensity), so a resumed run continues with the same
cache. The membership (each camera's exposure and place in it, each exposure's cameras) is also
kept on the device, so a training step completes its exposure without a host round trip
(:meth:`ExposureCache.complete_on_device`).
"""

from __future__ import annotations

from typing import Callable, Dict, List, Tuple

import torch
from torch import Tensor, nn

#: Marks cameras that belong to no exposure (novel views).
NO_EXPOSURE = -1


class ExposureCache(nn.Module):
    """Stale renders of the training latents, grouped by exposure."""

    def __init__(self, blurry_index: Tensor) -> None:
        """Args:
            blurry_index: long [N], the exposure of each training camera (-1: none).
        """
        super().__init__()
        self.register_buffer("blurry_index", blurry_index.reshape(-1).long().clone(), persistent=False)
        self.register_buffer("renders", torch.zeros(0, 0, 0, 3, dtype=torch.float16))
        # fixed at set-up, kept on the host: the exposure of each camera and each exposure's cameras
        self._exposure_of: List[int] = self.blurry_index.tolist()
        self._members: Dict[int, List[int]] = {}
        for camera, exposure in enumerate(self._exposure_of):
            if exposure != NO_EXPOSURE:
                self._members.setdefault(exposure, []).append(camera)
        # the same on the device: each camera's place in its exposure [N] (0 for none) and each
        # exposure's cameras [E, K] (K: the most of any exposure; -1 pads shorter ones)
        n_exposures = max(self._members, default=-1) + 1
        widest = max((len(m) for m in self._members.values()), default=0)
        table = torch.full((n_exposures, widest), NO_EXPOSURE, dtype=torch.long)
        place = torch.zeros(len(self._exposure_of), dtype=torch.long)
        for exposure, members in self._members.items():
            table[exposure, : len(members)] = torch.tensor(members, dtype=torch.long)
            place[members] = torch.arange(len(members))
        self.register_buffer("member_table", table, persistent=False)
        self.register_buffer("place_of", place, persistent=False)

    @property
    def filled(self) -> bool:
        return self.renders.shape[0] == self.blurry_index.shape[0]

    def members(self, exposure: int) -> List[int]:
        """The training cameras of ``exposure`` in camera order (= time order)."""
        return self._members[exposure]

    @torch.no_grad()
    def fill(self, image: Callable[[int], Tensor]) -> None:
        """Start every entry at ``image(i)``: [H, W, 3] linear training image of camera i."""
        first = image(0)
        renders = torch.empty(len(self.blurry_index), *first.shape, dtype=torch.float16, device=first.device)
        for i in range(len(self.blurry_index)):
            renders[i] = image(i)
        self.renders = renders

    def prepare_load(self, state_dict: dict, prefix: str) -> None:
        """Before ``load_state_dict``: resize the buffer to the checkpoint's; a checkpoint from
        before the cache existed gets the empty one (filled at the next blur-loss step)."""
        for name, value in self.state_dict().items():
            state_dict.setdefault(prefix + name, value)
        self.renders = torch.zeros_like(state_dict[prefix + "renders"], device=self.renders.device)

    def complete(self, indices: Tensor, live: Tensor) -> Dict[int, Tensor]:
        """The full latent stacks of the exposures the batch touches.

        Args:
            indices: long [B] training cameras of the batch.
            live: [B, H, W, 3] their renders (linear, with gradient).

        Returns:
            exposure -> [K, H, W, 3] stack (in first-seen order): the live renders at their places,
            the cached ones elsewhere.
        """
        if not self.filled:
            raise RuntimeError("ExposureCache.complete before fill")
        batch = indices.tolist()
        stacks: Dict[int, Tensor] = {}
        for exposure in self.exposures(indices):
            members = self.members(exposure)
            rows = [b for b, i in enumerate(batch) if self._exposure_of[i] == exposure]
            places = torch.tensor([members.index(batch[b]) for b in rows], device=live.device)
            cached = self.renders[torch.tensor(members, device=self.renders.device)].to(live.dtype)
            stacks[exposure] = cached.index_put((places,), live[torch.tensor(rows, device=live.device)])
        return stacks

    def complete_on_device(self, indices: Tensor, live: Tensor) -> Tuple[Tensor, Tensor]:
        """:meth:`complete` for a batch of one exposure (a training pair, a single latent), with no
        host round trip: the membership is read on the device.

        Args:
            indices: long [B] training cameras of the batch, all of one exposure (checked on the
                device, asynchronously: a batch that breaks it fails at a later synchronisation).
            live: [B, H, W, 3] their renders (linear, with gradient).

        Returns:
            stack [1, K, H, W, 3]: the exposure's latents, live renders at their places, cached
            ones elsewhere, zero past the exposure's own cameras (K: the most of any exposure);
            weights [1, K]: 1 for the exposure's cameras, 0 for that padding.
        """
        if not self.filled:
            raise RuntimeError("ExposureCache.complete_on_device before fill")
        idx = indices.to(self.member_table.device)
        exposure = self.blurry_index[idx]  # [B]
        torch._assert_async(((exposure == exposure[:1]) & (exposure != NO_EXPOSURE)).all())
        members = self.member_table[exposure[:1]][0]  # [K]
        valid = members != NO_EXPOSURE
        cached = self.renders[members.clamp_min(0).to(self.renders.device)].to(live.dtype)
        cached = cached * valid.to(cached)[:, None, None, None].to(cached.device)
        stack = cached.index_put((self.place_of[idx].to(live.device),), live)
        return stack[None], valid.to(device=live.device, dtype=live.dtype)[None]

    @torch.no_grad()
    def store(self, indices: Tensor, live: Tensor) -> None:
        """Remember the batch's renders [B, H, W, 3]."""
        self.renders[indices.to(self.renders.device)] = live.detach().to(self.renders.dtype)

    def exposures(self, indices: Tensor) -> List[int]:
        """The exposures the batch touches, in the order :meth:`complete` returns them."""
        exposures = [self._exposure_of[i] for i in indices.tolist()]
        return [e for e in dict.fromkeys(exposures) if e != NO_EXPOSURE]
