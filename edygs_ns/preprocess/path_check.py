"""Is the estimated camera path smooth? A cheap look at COLMAP's poses after mapping.

A camera filming a video moves smoothly: consecutive latents (k per exposure, then the next
exposure) are a small, steady step apart. When a moving object carries many of the features,
COLMAP can register a run of latents on it; their poses then drift away from the true path and
snap back where the background takes over again, a step many times the usual one (held-out
``three-objects`` seed 3: a 12.6x move and 19.8x turn between latents 0007_0 and 0007_1, the
path 0.12 units off; on the other suite scenes the largest step is under 4x the median). The
mover test (``colmap_movers``) uses the jumps to replace such a map; any left are reported, with
the latents around them, so the user can look at the poses before training on them. A path that
is smooth but wrong (COLMAP's frame following a mover that holds most features) is not seen here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Sequence

import numpy as np

#: A step (camera-centre distance or turn between consecutive latents) this many times the
#: median step is a jump.
JUMP_FACTOR = 5.0
#: Steps below this fraction of the median path step are not judged (a pause of the camera).
MIN_MEDIAN_STEP = 1e-9


@dataclass
class PathJump:
    """A jump of the estimated path between latents ``before`` and ``before + 1`` (indices into
    the time-ordered registered latents), ``factor`` times the median step, of ``kind`` "move" or "turn"."""

    before: int
    factor: float
    kind: str


def turn_angles_deg(c2w: np.ndarray) -> np.ndarray:
    """[N-1] angle (degrees) between consecutive camera rotations of c2w [N, 4, 4] (or [N, 3, 4])."""
    rot = c2w[:, :3, :3]
    cos = (np.einsum("nij,nij->n", rot[1:], rot[:-1]) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def path_jumps(c2w: np.ndarray, factor: float = JUMP_FACTOR) -> List[PathJump]:
    """Jumps of a time-ordered camera path c2w [N, 4, 4] (any consistent frame and scale): steps of
    the camera centre or turns over ``factor`` times their median over the path."""
    if len(c2w) < 3:
        return []
    jumps: List[PathJump] = []
    steps = {"move": np.linalg.norm(np.diff(c2w[:, :3, 3], axis=0), axis=1), "turn": turn_angles_deg(c2w)}
    for kind, step in steps.items():
        median = float(np.median(step))
        if median <= MIN_MEDIAN_STEP:
            continue
        for i in np.flatnonzero(step > factor * median):
            jumps.append(PathJump(int(i), float(step[i] / median), kind))
    return sorted(jumps, key=lambda j: (j.before, j.kind))


def jump_notice(jumps: List[PathJump], names: Sequence[str]) -> str:
    """One line for the user about the jumps (empty when there are none)."""
    if not jumps:
        return ""
    places: dict = {}
    for jump in jumps:
        places.setdefault(jump.before, []).append(f"{jump.kind} {jump.factor:.1f}x")
    described = [f"{names[i]} -> {names[i + 1]}: {', '.join(kinds)} the median step" for i, kinds in sorted(places.items())]
    listed = "; ".join(described[:3]) + (f"; and {len(described) - 3} more" if len(described) > 3 else "")
    return (f"warning: the estimated camera path jumps ({listed}): a moving object may have pulled COLMAP's poses "
            "near there; look at them (ns-viewer) before training, or give poses (--poses given)")


def registered_path_notice(c2w: np.ndarray, registered: np.ndarray, names: Sequence[str]) -> str:
    """``jump_notice`` for the registered latents of a time-ordered path (c2w [N, 4, 4], registered
    [N] bool, names [N]); empty when the path is smooth."""
    return jump_notice(path_jumps(c2w[registered]), [n for n, ok in zip(names, registered) if ok])
