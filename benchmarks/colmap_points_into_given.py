"""A given-pose scene started from COLMAP's points instead of its own: issue 16's strict comparison.

    python benchmarks/colmap_points_into_given.py SCENE_GIVEN SCENE_COLMAP OUT

SCENE_GIVEN and SCENE_COLMAP are ``edygs-process`` outputs of one capture (``--poses given`` and
``--poses colmap``). OUT (which must not exist) is a copy of SCENE_GIVEN whose initial points are
SCENE_COLMAP's, moved into the given poses' frame by the Sim(3) that maps COLMAP's poses onto the
given ones (``geometry.pose_sim3``, latents matched by file name). Prints the Sim(3)'s scale, the
camera-centre residual it leaves and the point count.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path
from typing import Dict, Tuple

import numpy as np

from edygs_ns.geometry import pose_sim3
from edygs_ns.io.ply import read_ply_points, write_ply_points


def scene_poses(scene: Path) -> Tuple[Dict[str, np.ndarray], dict]:
    """{latent file name: [4, 4] camera-to-world} of a processed scene, and its transforms.json."""
    transforms = json.loads((scene / "transforms.json").read_text())
    return {Path(f["file_path"]).name: np.asarray(f["transform_matrix"], dtype=np.float64) for f in transforms["frames"]}, transforms


def main() -> None:
    if len(sys.argv) != 4:
        raise SystemExit(__doc__)
    given, colmap, out = (Path(p) for p in sys.argv[1:4])
    if out.exists():
        raise SystemExit(f"colmap_points_into_given: {out} exists; choose a new folder")
    try:
        poses_given, transforms = scene_poses(given)
        poses_colmap, transforms_colmap = scene_poses(colmap)
        names = sorted(set(poses_given) & set(poses_colmap))
        src = np.stack([poses_colmap[n] for n in names])
        dst = np.stack([poses_given[n] for n in names])
        scale, rot, trans = pose_sim3(src, dst)
        xyz, rgb = read_ply_points(colmap / transforms_colmap["ply_file_path"])
    except (OSError, KeyError, ValueError) as err:
        raise SystemExit(f"colmap_points_into_given: {err}")
    residual = np.linalg.norm(scale * src[:, :3, 3] @ rot.T + trans - dst[:, :3, 3], axis=1).mean()
    print(f"{len(names)} poses matched; Sim(3) scale {scale:.4f}; camera-centre residual mean {residual:.4f}; {len(xyz)} points")
    shutil.copytree(given, out, symlinks=True)
    write_ply_points(out / transforms["ply_file_path"], scale * xyz @ rot.T + trans, rgb)


if __name__ == "__main__":
    main()
