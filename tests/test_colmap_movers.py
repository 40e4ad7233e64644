"""The mover test of edygs-process (edygs_ns.preprocess.colmap_movers): candidate clusters, their
image footprints, and the filtered database COLMAP maps again."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from edygs_ns.preprocess.colmap_movers import MoverTest, Remap, choose, filtered_database, footprint, point_clusters


def test_point_clusters_find_two_separate_groups_and_repeat() -> None:
    rng = np.random.default_rng(0)
    room = rng.normal([0.0, 0.0, 5.0], 0.3, size=(120, 3))
    mover = rng.normal([2.0, 0.5, 2.0], 0.2, size=(80, 3))
    xyz = np.concatenate([room, mover])
    clusters = point_clusters(xyz, max_clusters=4)
    assert len(clusters) == 2 + 3 + 4
    as_sets = [set(c.tolist()) for c in clusters]
    assert set(range(120, 200)) in as_sets[:2], "K = 2 splits the two groups exactly"
    for c in clusters:
        assert 0 < len(c) < len(xyz)
    again = point_clusters(xyz, max_clusters=4)
    assert all(np.array_equal(a, b) for a, b in zip(clusters, again))
    assert point_clusters(xyz[:3], max_clusters=4) == [], "too few points for any K"
    assert point_clusters(xyz, max_clusters=1) == []


def test_footprint_is_the_hull_widened_by_the_margin() -> None:
    square = np.array([[20.0, 10.0], [40.0, 10.0], [40.0, 30.0], [20.0, 30.0], [30.0, 20.0]])
    hull = footprint(square, (64, 48), margin_px=0.0)
    assert hull.shape == (48, 64) and hull[20, 30] and hull[11, 21] and not hull[5, 30]
    wide = footprint(square, (64, 48), margin_px=3.0)
    assert wide[8, 30] and wide[20, 17] and wide[20, 43] and not wide[4, 30], "about 3 px outside the hull, not 6"
    assert (wide >= hull).all()
    assert not footprint(square[:2], (64, 48), 3.0).any(), "two points make no footprint"
    line = np.array([[5.0, 5.0], [15.0, 5.0], [25.0, 5.0]])
    assert footprint(line, (64, 48), 2.0)[5, 15], "collinear points give a thin band, not an error"


def _database_with_matches(path: Path) -> None:
    """A COLMAP database of two images, four keypoints each, matched 0-0 .. 3-3 (verified)."""
    import pycolmap

    database = pycolmap.Database.open(str(path))
    camera = pycolmap.Camera(model="SIMPLE_PINHOLE", width=64, height=48, params=[50.0, 32.0, 24.0])
    camera_id = database.write_camera(camera)
    keypoints = np.array([[5.0, 5.0], [10.0, 40.0], [50.0, 10.0], [60.0, 40.0]], np.float32)
    ids = []
    for name in ("a.png", "b.png"):
        image = pycolmap.Image(name=name, camera_id=camera_id)
        ids.append(database.write_image(image))
        database.write_keypoints(ids[-1], keypoints)
    geometry = pycolmap.TwoViewGeometry()
    geometry.config = 2  # calibrated
    geometry.inlier_matches = np.array([[0, 0], [1, 1], [2, 2], [3, 3]], np.uint32)
    database.write_two_view_geometry(ids[0], ids[1], geometry)
    database.close()


def test_filtered_database_drops_only_matches_on_the_footprint(tmp_path: Path) -> None:
    pytest.importorskip("pycolmap")
    import pycolmap

    source = tmp_path / "source.db"
    _database_with_matches(source)
    dropped = {1: np.array([False, False, True, False]), 2: np.array([False, False, False, True])}
    filtered_database(source, tmp_path / "copy" / "database.db", dropped)
    copy = pycolmap.Database.open(str(tmp_path / "copy" / "database.db"))
    kept = copy.read_two_view_geometry(1, 2).inlier_matches.tolist()
    assert copy.num_keypoints_for_image(1) == 4, "keypoints stay; only their matches go"
    copy.close()
    assert kept == [[0, 0], [1, 1]]
    original = pycolmap.Database.open(str(source))
    assert original.read_two_view_geometry(1, 2).inlier_matches.shape[0] == 4, "the source is left unchanged"
    original.close()


def test_mover_test_message_says_what_it_did() -> None:
    kept = MoverTest(14, 0.33, 0.26, 1900, 3967, True, 0.83, 1.25, 1.15)
    assert "1,900 of 3,967 points (48%)" in kept.message() and "0.330 -> 0.260 px" in kept.message()
    assert "tracks x1.25 longer" in kept.message()
    assert kept.as_dict()["kept"] is True
    stayed = MoverTest(14, 0.27, 0.26, 400, 2672, False, 0.83, 0.97, 1.15)
    assert stayed.message().startswith("mover test: no group") and "14 clusters" in stayed.message()
    assert "skipped" in MoverTest(0, 0.27, float("nan"), 0, 2, False, 0.85).message()


def test_a_jumping_path_is_replaced_by_the_best_smooth_remap() -> None:
    """Error and tracks decide first (most points among the passing re-maps); a first map whose
    path jumps gives way to the lowest-error smooth re-map that beats its error, else it stands."""
    remaps = [Remap(0.90, 1.05, 2000, 500, True), Remap(0.86, 1.10, 1500, 900, False), Remap(0.95, 0.98, 2300, 300, True)]
    assert choose(remaps, 1.0, first_smooth=True, error_ratio=0.83, track_ratio=1.15) == (None, "")
    assert choose(remaps, 1.0, first_smooth=False, error_ratio=0.83, track_ratio=1.15) == (0, "path")
    assert choose(remaps[1:2], 1.0, first_smooth=False, error_ratio=0.83, track_ratio=1.15) == (None, ""), "no smooth re-map"
    assert choose(remaps[2:], 0.9, first_smooth=False, error_ratio=0.83, track_ratio=1.15) == (None, ""), "not better"
    passing = remaps + [Remap(0.80, 1.20, 1200, 1000, False), Remap(0.82, 1.16, 1800, 600, True)]
    assert choose(passing, 1.0, first_smooth=False, error_ratio=0.83, track_ratio=1.15) == (4, "error")


def test_mover_test_message_names_the_jump() -> None:
    kept = MoverTest(14, 0.31, 0.27, 1012, 2575, True, 0.83, 1.11, 1.15, first_jumps=2, kept_for="path")
    assert "path jumps (2 step(s))" in kept.message() and "1,012 of 2,575 points" in kept.message()
    assert kept.as_dict()["kept_for"] == "path" and kept.as_dict()["first_map_jumps"] == 2


def test_a_large_mover_no_longer_carries_colmaps_path(tmp_path: Path) -> None:
    """edygs-synth's `large` preset (a textured ellipsoid on about a third of the image): COLMAP alone
    follows it, the mover test finds it among the points and re-maps without it."""
    import json
    from dataclasses import replace

    from edygs_ns.eval.trajectory import ate_rmse
    from edygs_ns.events.edi import EdiConfig
    from edygs_ns.preprocess.colmap import ColmapConfig
    from edygs_ns.preprocess.inputs import InputConfig
    from edygs_ns.preprocess.pipeline import ProcessConfig, process
    from edygs_ns.sim.writer import SynthConfig, write_synthetic_scene

    raw = write_synthetic_scene(SynthConfig(output_dir=tmp_path / "raw", preset="large", width=160, height=120,
                                            n_frames=6, k=3, supersample=1, sim_steps_per_exposure=8,
                                            n_subframes=5, novel_stride=3))
    truth = {(f["blurry_index"], f["latent_index"]): f["transform_matrix"]
             for f in json.loads((raw / "gt" / "transforms.json").read_text())["frames"]}
    diameter = json.loads((raw / "scene.json").read_text())["camera_path_diameter"]
    ate, reports = {}, {}
    for name, clusters in (("without", 0), ("with", ColmapConfig().mover_clusters)):
        config = ProcessConfig(output=tmp_path / name, inputs=InputConfig(exposures=raw / "exposures.csv",
                                                                        events=raw / "events.h5"),
                               edi=EdiConfig(k=3), colmap=ColmapConfig(mover_clusters=clusters))
        reports[name] = process(config)
        frames = json.loads((tmp_path / name / "transforms.json").read_text())["frames"]
        estimate = np.array([f["transform_matrix"] for f in frames])
        gt = np.array([truth[(f["blurry_index"], f["latent_index"])] for f in frames])
        ate[name] = ate_rmse(estimate, gt) / diameter
    assert reports["without"]["mover_test"] is None
    test = reports["with"]["mover_test"]
    assert test["kept"] and test["best_error_px"] < test["error_ratio_needed"] * test["error_before_px"]
    assert test["track_gain"] >= test["track_gain_needed"]
    assert 0.2 < test["best_cluster_points"] / test["points"] < 0.8, "a cluster, not the whole map"
    assert ate["without"] > 0.04, f"COLMAP alone should follow the mover here: ATE {ate['without']:.3f} of the path"
    assert ate["with"] < 0.5 * ate["without"] and ate["with"] < 0.025, ate
