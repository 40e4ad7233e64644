"""A large moving object can carry COLMAP's frame along; find it among the map's points and re-map
without it.

With a mover on a third of the image (the suite's ``large`` preset) the incremental mapper settles
on a compromise: one rigid scene that explains room and mover together within about a pixel, on a
camera path 0.2 units off the truth. Per image pair the two motions cannot be told apart (a
compromise fundamental matrix fits both), but the compromise is the looser fit: mapped without the
mover's features, the same images give a map whose mean reprojection error is about 20 % lower,
with longer tracks and the true path (docs/experiments.md, session 17).

The test: the first map's 3-D points are clustered by k-means for K = 2 .. ``max_clusters``; each
cluster is a candidate mover. For each, a copy of the database loses the verified matches whose
keypoint lies on the cluster's footprint in that image (the convex hull of its observations,
widened by ``margin_px``), and is mapped again. A candidate's map passes when its mean reprojection
error is at most ``error_ratio`` times the first map's, its mean track length at least
``track_ratio`` times the first map's (a consistent scene keeps its features tracked longer; on
the suite the re-maps that come closest without a large mover lower the error but not the
tracks), and it registers as many images. Of those that pass, the map with the most points is
kept (it explains the most of the scene: on ``large`` the K = 2 cluster, two thirds of all
points, passes too but drops much of the room with the mover). Otherwise the first map stands.
Features and matches are not recomputed.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Tuple

import numpy as np

#: Database file name inside each candidate's folder.
DATABASE = "database.db"
#: Fewest observations of a cluster in one image that get a footprint (a hull needs 3 points).
MIN_HULL_POINTS = 3


@dataclass
class MoverTest:
    """Outcome of the mover test on one map.

    Attributes:
        candidates: clusters tried (re-maps run).
        error_before: mean reprojection error of the first map (COLMAP pixels).
        best_error: the kept candidate's error, else the lowest among the candidates' maps (NaN
            when none mapped).
        best_points: size of that candidate's cluster (3-D points of the first map).
        total_points: points of the first map.
        kept: whether the candidate's map replaced the first one.
        ratio_needed: the error ratio a candidate had to reach.
        track_gain: the kept (else the lowest-error) candidate's mean track length over the first map's.
        track_gain_needed: the track-length ratio a candidate had to reach.
    """

    candidates: int
    error_before: float
    best_error: float
    best_points: int
    total_points: int
    kept: bool
    ratio_needed: float
    track_gain: float = float("nan")
    track_gain_needed: float = 1.0

    @property
    def best_ratio(self) -> float:
        return self.best_error / self.error_before if self.error_before > 0 else float("nan")

    def message(self) -> str:
        """One line for the console and the report."""
        if self.candidates == 0:
            return "mover test: skipped (too few points to cluster)"
        share = self.best_points / max(self.total_points, 1)
        if self.kept:
            return (f"mover test: {self.best_points:,} of {self.total_points:,} points ({share:.0%}) move with an object; "
                    f"re-mapped without them, reprojection error {self.error_before:.3f} -> {self.best_error:.3f} px "
                    f"(x{self.best_ratio:.2f}, needed <= x{self.ratio_needed:.2f}), tracks x{self.track_gain:.2f} longer")
        return (f"mover test: no group of points moves with an object ({self.candidates} clusters tried, best error "
                f"x{self.best_ratio:.2f} of {self.error_before:.3f} px with tracks x{self.track_gain:.2f}; needed <= "
                f"x{self.ratio_needed:.2f} with tracks >= x{self.track_gain_needed:.2f})")

    def as_dict(self) -> Dict[str, Any]:
        return {"candidates": self.candidates, "error_before_px": self.error_before,
                "best_error_px": None if not np.isfinite(self.best_error) else self.best_error,
                "best_cluster_points": self.best_points, "points": self.total_points, "kept": self.kept,
                "error_ratio_needed": self.ratio_needed,
                "track_gain": None if not np.isfinite(self.track_gain) else self.track_gain,
                "track_gain_needed": self.track_gain_needed}


def point_clusters(xyz: np.ndarray, max_clusters: int, seed: int = 0) -> List[np.ndarray]:
    """Candidate movers: every cluster of k-means on the points for K = 2 .. max_clusters.

    Args:
        xyz: [P, 3] points.
        max_clusters: largest K (below 2: no candidates).
        seed: k-means seed (the clusters repeat exactly).

    Returns:
        Index arrays into ``xyz``, non-empty and not the whole set, at most sum(K) of them.
    """
    from scipy.cluster.vq import kmeans2

    out: List[np.ndarray] = []
    for k in range(2, max_clusters + 1):
        if len(xyz) < 2 * k:
            break
        _, labels = kmeans2(np.asarray(xyz, np.float64), k, seed=seed, minit="++")
        for c in range(k):
            members = np.flatnonzero(labels == c)
            if 0 < len(members) < len(xyz):
                out.append(members)
    return out


def footprint(xy: np.ndarray, size: Tuple[int, int], margin_px: float) -> np.ndarray:
    """[H, W] bool: the convex hull of image points ``xy`` [M, 2] (pixels, x right, y down),
    widened by ``margin_px``; empty with fewer than MIN_HULL_POINTS points."""
    from PIL import Image, ImageDraw
    from scipy.spatial import ConvexHull, QhullError

    width, height = size
    canvas = Image.new("L", (width, height), 0)
    if len(xy) >= MIN_HULL_POINTS:
        try:
            corners = xy[ConvexHull(xy, qhull_options="QJ").vertices]
        except QhullError:  # degenerate even joggled: keep the points themselves
            corners = xy
        polygon = [tuple(map(float, p)) for p in corners]
        draw = ImageDraw.Draw(canvas)
        draw.polygon(polygon, fill=1)
        width_px = max(1, int(round(2.0 * margin_px)))
        draw.line(polygon + [polygon[0]], fill=1, width=width_px, joint="curve")
    return np.asarray(canvas, dtype=bool)


def _dropped_keypoints(model: Any, members: np.ndarray, point_ids: np.ndarray, keypoints: Dict[int, np.ndarray],
                       size: Tuple[int, int], margin_px: float) -> Dict[int, np.ndarray]:
    """Per image id, [K_i] bool: keypoints on the footprint of the cluster ``members``."""
    per_image: Dict[int, List[np.ndarray]] = {}
    for pid in point_ids[members]:
        for element in model.points3D[int(pid)].track.elements:
            image = model.images[element.image_id]
            per_image.setdefault(element.image_id, []).append(np.asarray(image.points2D[element.point2D_idx].xy))
    dropped = {}
    for image_id, kp in keypoints.items():
        if len(per_image.get(image_id, ())) < MIN_HULL_POINTS:  # no footprint in this image
            dropped[image_id] = np.zeros(len(kp), dtype=bool)
            continue
        hull = footprint(np.array(per_image[image_id]), size, margin_px)
        col = np.clip(np.floor(kp[:, 0]).astype(int), 0, size[0] - 1)
        row = np.clip(np.floor(kp[:, 1]).astype(int), 0, size[1] - 1)
        dropped[image_id] = hull[row, col]
    return dropped


def filtered_database(source: Path, target: Path, dropped: Dict[int, np.ndarray]) -> None:
    """Copy ``source`` to ``target`` without the verified matches that touch a dropped keypoint."""
    import pycolmap

    target.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(source, target)
    database = pycolmap.Database.open(str(target))
    try:
        pair_ids, geometries = database.read_two_view_geometries()
        for pair_id, geometry in zip(pair_ids, geometries):
            first, second = pycolmap.pair_id_to_image_pair(pair_id)
            matches = geometry.inlier_matches
            keep = ~(dropped[first][matches[:, 0]] | dropped[second][matches[:, 1]])
            if not keep.all():
                geometry.inlier_matches = matches[keep]
                database.update_two_view_geometry(first, second, geometry)
    finally:
        database.close()


def largest_model(models: Dict[int, Any]) -> Optional[Any]:
    """The model that registered the most images (None when there is none)."""
    return max(models.values(), key=lambda r: r.num_reg_images()) if models else None


def remap_without_movers(database: Path, model: Any, work: Path, remap: Callable[[Path, Path], Dict[int, Any]],
                         max_clusters: int, error_ratio: float, track_ratio: float, margin_px: float,
                         advance: Callable[[], None] = lambda: None) -> Tuple[Any, MoverTest]:
    """Run the mover test on ``model`` (a pycolmap Reconstruction mapped from ``database``).

    Args:
        database: the COLMAP database the model was mapped from (left unchanged).
        model: the first map.
        work: scratch folder (replaced; removed afterwards).
        remap: maps a database into a sparse folder, returning COLMAP's models.
        max_clusters: k-means runs for K = 2 .. max_clusters.
        error_ratio: a candidate's map passes at most at this times the first map's error ...
        track_ratio: ... and with tracks at least this times as long on average.
        margin_px: footprint margin, pixels of the images COLMAP saw.
        advance: called once per candidate (progress).

    Returns:
        (the map to use, the test's outcome).
    """
    import pycolmap

    point_ids = np.array(sorted(model.points3D.keys()), dtype=np.int64)
    xyz = np.array([model.points3D[int(p)].xyz for p in point_ids]).reshape(-1, 3)
    error_before = float(model.compute_mean_reprojection_error())
    tracks_before = float(model.compute_mean_track_length())
    clusters = point_clusters(xyz, max_clusters)
    camera = next(iter(model.cameras.values()))
    size = (int(camera.width), int(camera.height))
    source = pycolmap.Database.open(str(database))
    try:
        keypoints = {image.image_id: np.asarray(source.read_keypoints(image.image_id))[:, :2]
                     for image in source.read_all_images()}
    finally:
        source.close()
    if work.exists():
        shutil.rmtree(work)
    lowest: Tuple[float, int, float] = (float("inf"), 0, float("nan"))
    kept: Optional[Tuple[float, int, float, Any]] = None
    try:
        for index, members in enumerate(clusters):
            folder = work / f"candidate_{index:02d}"
            dropped = _dropped_keypoints(model, members, point_ids, keypoints, size, margin_px)
            filtered_database(database, folder / DATABASE, dropped)
            candidate = largest_model(remap(folder / DATABASE, folder / "sparse"))
            advance()
            if candidate is None or candidate.num_reg_images() < model.num_reg_images() or candidate.num_points3D() == 0:
                continue
            error = float(candidate.compute_mean_reprojection_error())
            gain = float(candidate.compute_mean_track_length()) / max(tracks_before, 1e-12)
            lowest = min(lowest, (error, len(members), gain))
            passes = error <= error_ratio * error_before and gain >= track_ratio
            if passes and (kept is None or candidate.num_points3D() > kept[3].num_points3D()):
                kept = (error, len(members), gain, candidate)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    error, size, gain = kept[:3] if kept is not None else lowest
    outcome = MoverTest(len(clusters), error_before, error if np.isfinite(error) else float("nan"), size,
                        len(point_ids), kept is not None, error_ratio, gain, track_ratio)
    return (kept[3] if kept is not None else model), outcome
