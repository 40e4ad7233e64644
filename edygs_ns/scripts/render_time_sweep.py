"""Bullet-time sweep: one fixed viewpoint, time swept over the clip -> PNG frames + mp4.

`edygs-render-sweep --load-config RUN/config.yml --output-dir DIR --camera-index I` renders the
training camera I (at its refined pose by default) at `num_frames` evenly spaced times from
`time_start` to `time_end` (normalised clip time) and writes

    DIR/frames/00000.png ...    the chosen outputs side by side (default rgb | motion mask)
    DIR/sweep.mp4               the same frames as an H.264 video (needs ffmpeg; mediapy)

Single-channel outputs use nerfstudio's colormaps: grey for the motion mask and accumulation,
turbo for depth with one near/far range over the whole sweep (no per-frame flicker).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
import tyro
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.utils import colormaps
from nerfstudio.utils.rich_utils import CONSOLE, get_progress
from torch import Tensor

from edygs_ns.eval.pose_alignment import refined_train_poses, with_poses
from edygs_ns.io.images import UINT8_MAX

#: Frames of the default sweep.
DEFAULT_NUM_FRAMES = 30
#: Default outputs rendered side by side.
DEFAULT_OUTPUTS: Tuple[str, ...] = ("rgb", "mask")
#: Colormap per single-channel output (others: nerfstudio's default).
GREY_OUTPUTS: Tuple[str, ...] = ("mask", "accumulation")
GREY_COLORMAP = "gray"
DEPTH_COLORMAP = "turbo"
#: Output names inside the output folder.
FRAMES_DIR = "frames"
VIDEO_NAME = "sweep.mp4"
FRAME_PATTERN = "{index:05d}.png"
#: H.264 with 4:2:0 chroma needs even frame sides: frames are padded by up to this many pixels.
VIDEO_SIDE_MULTIPLE = 2


def sweep_times(num_frames: int, time_start: float = 0.0, time_end: float = 1.0) -> np.ndarray:
    """[T] evenly spaced normalised times from `time_start` to `time_end` (both included)."""
    if num_frames < 1:
        raise ValueError(f"num_frames must be >= 1, got {num_frames}")
    for name, value in (("time_start", time_start), ("time_end", time_end)):
        if not 0.0 <= value <= 1.0:
            raise ValueError(f"{name} must be in [0, 1] (normalised clip time), got {value}")
    return np.linspace(time_start, time_end, num_frames)


def sweep_cameras(camera: Cameras, times: Sequence[float]) -> Cameras:
    """The single camera `camera` [1] repeated at every time of `times` -> Cameras [T]."""
    if camera.shape[0] != 1:
        raise ValueError(f"sweep_cameras needs one camera, got {camera.shape[0]}")
    count = len(times)
    expand = lambda t: t.expand(count, *t.shape[1:])  # noqa: E731 - one-line broadcast helper
    return Cameras(
        camera_to_worlds=expand(camera.camera_to_worlds), fx=expand(camera.fx), fy=expand(camera.fy),
        cx=expand(camera.cx), cy=expand(camera.cy), width=expand(camera.width), height=expand(camera.height),
        camera_type=expand(camera.camera_type),
        times=torch.as_tensor(np.asarray(times, dtype=np.float32)).reshape(count, 1).to(camera.device),
    )


def render_outputs(model: Any, cameras: Cameras, output_names: Sequence[str]) -> Dict[str, List[Tensor]]:
    """Render every camera of `cameras` [T]; returns name -> T tensors [H, W, C] on the CPU."""
    frames: Dict[str, List[Tensor]] = {name: [] for name in output_names}
    cameras = cameras.to(model.device)
    with get_progress("Rendering time sweep", suffix="fps") as progress:
        for i in progress.track(range(cameras.shape[0]), total=cameras.shape[0]):
            outputs = model.get_outputs_for_camera(cameras[i : i + 1])
            for name in output_names:
                if name not in outputs:
                    raise ValueError(f"the model has no output {name!r}; it renders {sorted(outputs)}")
                frames[name].append(outputs[name].detach().float().cpu())
            if "depth" in output_names and "accumulation" in outputs:
                frames.setdefault("_accumulation", []).append(outputs["accumulation"].detach().float().cpu())
    return frames


def colorize(frames: Dict[str, List[Tensor]], output_names: Sequence[str]) -> List[np.ndarray]:
    """Turn raw outputs into uint8 [H, W * len(output_names), 3] frames, outputs side by side."""
    coloured: Dict[str, List[Tensor]] = {}
    for name in output_names:
        images = frames[name]
        if name == "depth":
            near = min(float(d.min()) for d in images)
            far = max(float(d.max()) for d in images)
            accumulation = frames.get("_accumulation")
            options = colormaps.ColormapOptions(colormap=DEPTH_COLORMAP)
            coloured[name] = [
                colormaps.apply_depth_colormap(d, accumulation=accumulation[i] if accumulation else None,
                                               near_plane=near, far_plane=far, colormap_options=options)
                for i, d in enumerate(images)
            ]  # fmt: skip
        else:
            options = colormaps.ColormapOptions(colormap=GREY_COLORMAP if name in GREY_OUTPUTS else "default")
            coloured[name] = [colormaps.apply_colormap(img.clamp(0.0, 1.0), colormap_options=options) for img in images]
    count = len(coloured[output_names[0]])
    out = []
    for i in range(count):
        row = torch.cat([coloured[name][i] for name in output_names], dim=1)
        out.append((row.clamp(0.0, 1.0) * UINT8_MAX).round().to(torch.uint8).numpy())
    return out


def _pad_even(frame: np.ndarray) -> np.ndarray:
    pad_h = (-frame.shape[0]) % VIDEO_SIDE_MULTIPLE
    pad_w = (-frame.shape[1]) % VIDEO_SIDE_MULTIPLE
    return np.pad(frame, ((0, pad_h), (0, pad_w), (0, 0))) if pad_h or pad_w else frame


def write_sweep(frames: Sequence[np.ndarray], output_dir: Path, fps: float, video: bool = True) -> Tuple[List[Path], Optional[Path]]:
    """Write PNG frames (and an mp4 when `video` and ffmpeg is installed).

    Returns:
        (PNG paths, mp4 path or None).
    """
    import mediapy

    output_dir = Path(output_dir)
    frame_dir = output_dir / FRAMES_DIR
    frame_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, frame in enumerate(frames):
        path = frame_dir / FRAME_PATTERN.format(index=i)
        mediapy.write_image(path, frame, fmt="png")
        paths.append(path)
    if not video:
        return paths, None
    if shutil.which("ffmpeg") is None:
        CONSOLE.print("[bold yellow]edygs-render-sweep: ffmpeg not found, no mp4 written (apt-get install ffmpeg)")
        return paths, None
    video_path = output_dir / VIDEO_NAME
    mediapy.write_video(video_path, [_pad_even(f) for f in frames], fps=fps)
    return paths, video_path


def render_time_sweep(
    pipeline: Any,
    output_dir: Path,
    camera_index: int = 0,
    times: Optional[Sequence[float]] = None,
    output_names: Sequence[str] = DEFAULT_OUTPUTS,
    refined_pose: bool = True,
    fps: float = 10.0,
    video: bool = True,
) -> Tuple[List[Path], Optional[Path]]:
    """Render training camera `camera_index` of a loaded pipeline at every time of `times`.

    Args:
        pipeline: a loaded nerfstudio pipeline (its train dataset holds the cameras).
        output_dir: where frames/ and sweep.mp4 go.
        camera_index: index of the training camera giving the viewpoint.
        times: normalised times; default 30 evenly spaced over [0, 1].
        output_names: model outputs drawn side by side (e.g. rgb, mask, rgb_static, depth).
        refined_pose: use the pose refined during training (else the dataparser pose).
        fps: video frame rate.
        video: also write the mp4.

    Returns:
        (PNG paths, mp4 path or None).
    """
    if not output_names:
        raise ValueError("render_time_sweep: no output name given")
    cameras = pipeline.datamanager.train_dataset.cameras
    if not 0 <= camera_index < cameras.shape[0]:
        raise ValueError(f"camera_index {camera_index} is out of range: the run has {cameras.shape[0]} training cameras")
    if refined_pose:
        cameras = with_poses(cameras, refined_train_poses(pipeline.model, cameras))
    else:
        cameras = with_poses(cameras, cameras.camera_to_worlds)
    times = sweep_times(DEFAULT_NUM_FRAMES) if times is None else np.asarray(times, dtype=np.float64)
    pipeline.model.eval()
    raw = render_outputs(pipeline.model, sweep_cameras(cameras[camera_index : camera_index + 1], times), output_names)
    paths, video_path = write_sweep(colorize(raw, output_names), output_dir, fps, video)
    CONSOLE.log(f"edygs-render-sweep: {len(paths)} frames in {Path(output_dir) / FRAMES_DIR}" + (f", video {video_path}" if video_path else ""))
    return paths, video_path


@dataclass
class RenderTimeSweep:
    """Bullet time: render one training viewpoint while time runs over the clip."""

    load_config: Path
    """The run's config.yml (written by ns-train)."""
    output_dir: Path = Path("renders/time_sweep")
    """Folder for frames/ and sweep.mp4."""
    camera_index: int = 0
    """Training camera giving the fixed viewpoint."""
    num_frames: int = DEFAULT_NUM_FRAMES
    """Number of time samples."""
    time_start: float = 0.0
    """First time (normalised to [0, 1] over the clip)."""
    time_end: float = 1.0
    """Last time (normalised)."""
    fps: float = 10.0
    """Video frame rate."""
    rendered_output_names: Tuple[str, ...] = field(default_factory=lambda: DEFAULT_OUTPUTS)
    """Model outputs drawn side by side: rgb, mask, rgb_static, depth, accumulation."""
    refined_pose: bool = True
    """Use the training camera's refined pose (else its dataparser pose)."""
    video: bool = True
    """Also write sweep.mp4 (needs ffmpeg)."""

    def main(self) -> Tuple[List[Path], Optional[Path]]:
        """Load the run and render the sweep."""
        from nerfstudio.utils.eval_utils import eval_setup

        from edygs_ns.compat import allow_nerfstudio_checkpoints

        if not Path(self.load_config).is_file():
            raise FileNotFoundError(f"edygs-render-sweep: run config {self.load_config} does not exist (pass RUN/config.yml)")
        allow_nerfstudio_checkpoints()
        _, pipeline, _, _ = eval_setup(Path(self.load_config), test_mode="test")
        return render_time_sweep(
            pipeline, self.output_dir, self.camera_index, sweep_times(self.num_frames, self.time_start, self.time_end),
            self.rendered_output_names, self.refined_pose, self.fps, self.video,
        )  # fmt: skip


def entrypoint() -> None:
    """Console script `edygs-render-sweep`."""
    tyro.cli(RenderTimeSweep).main()


if __name__ == "__main__":
    entrypoint()
