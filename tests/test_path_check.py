"""Jumps of the estimated camera path (preprocess/path_check.py)."""

from __future__ import annotations

import numpy as np

from edygs_ns.preprocess.path_check import jump_notice, path_jumps


def _path(n: int = 40) -> np.ndarray:
    """A smooth sideways dolly with a slow pan: c2w [n, 4, 4]."""
    c2w = np.tile(np.eye(4), (n, 1, 1))
    t = np.linspace(0.0, 1.0, n)
    c2w[:, 0, 3] = 2.0 * t
    c2w[:, 2, 3] = 0.3 * np.sin(3.0 * t)
    for i, a in enumerate(0.4 * t):
        c2w[i, :3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    return c2w


def test_a_smooth_path_has_no_jump():
    assert path_jumps(_path()) == []
    assert jump_notice([], []) == ""


def test_a_drifted_run_of_latents_is_reported_where_it_snaps_back():
    c2w = _path()
    c2w[20:27, :3, 3] += np.linspace(0.05, 0.5, 7)[:, None] * np.array([0.0, 1.0, 0.0])  # drifts, then snaps back
    jumps = path_jumps(c2w)
    assert [(j.before, j.kind) for j in jumps] == [(26, "move")]
    names = [f"{i:04d}" for i in range(len(c2w))]
    notice = jump_notice(jumps, names)
    assert "0026 -> 0027" in notice and "--poses given" in notice and "\n" not in notice


def test_a_sudden_turn_is_a_jump_too():
    c2w = _path()
    a = 0.5
    c2w[30:, :3, :3] = c2w[30:, :3, :3] @ np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    assert [(j.before, j.kind) for j in path_jumps(c2w)] == [(29, "turn")]
