"""edygs-process never loses data and says what it did: --overwrite staging, interrupted runs,
truthful messages, dropped frames, static cameras caught before COLMAP, one-line errors."""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from capture_fixtures import EXPOSURE_US, PERIOD_US, write_tiny_capture
from edygs_ns.events.edi import EdiConfig
from edygs_ns.preprocess import motion_check
from edygs_ns.preprocess.inputs import InputConfig
from edygs_ns.preprocess.steps import STEP_RECORD_NAME
from edygs_ns.preprocess import pipeline as pipeline_module
from edygs_ns.scripts.process import entrypoint
from edygs_ns.preprocess.pipeline import ProcessConfig, WORK_DIR_NAME, process

K = 3
#: Few random points keep the tiny runs fast.
POINTS = 50


def _config(cap, output: Path, **inputs) -> ProcessConfig:
    given = dict(exposures=cap.csv, events=cap.events, given_poses=cap.poses)
    given.update(inputs)
    return ProcessConfig(output=output, inputs=InputConfig(**given), edi=EdiConfig(k=K), poses="given",
                         num_random_points=POINTS)


@pytest.fixture
def cap(tmp_path: Path):
    return write_tiny_capture(tmp_path / "raw", n=4)


def _siblings(folder: Path) -> list:
    return sorted(p.name for p in folder.parent.iterdir() if p.name.startswith(f".{folder.name}"))


def test_failed_overwrite_keeps_the_previous_scene(cap, tmp_path: Path) -> None:
    scene = tmp_path / "scene"
    process(_config(cap, scene))
    before = (scene / "transforms.json").read_bytes()
    typo = _config(cap, scene, exposures=cap.root / "exposure.csv")
    with pytest.raises(FileNotFoundError, match=r"exposure\.csv: exposure table not found"):
        process(replace(typo, overwrite=True))
    assert (scene / "transforms.json").read_bytes() == before and (scene / "event_maps.npy").is_file()
    assert _siblings(scene) == []


def test_overwrite_swaps_in_the_new_scene_and_keeps_foreign_files(cap, tmp_path: Path) -> None:
    scene = tmp_path / "scene"
    process(_config(cap, scene))
    (scene / "notes.txt").write_text("mine")
    report = process(replace(_config(cap, scene), edi=EdiConfig(k=2), overwrite=True))
    meta = json.loads((scene / "transforms.json").read_text())
    assert meta["k"] == 2 and report["steps_reused"] == [] and (scene / "notes.txt").read_text() == "mine"
    assert json.loads((scene / "process_report.json").read_text())["k"] == 2
    assert _siblings(scene) == []


def test_interrupted_runs_are_cleaned_up_or_resumed(cap, tmp_path: Path) -> None:
    scene = tmp_path / "scene"
    (scene / WORK_DIR_NAME / "blurry").mkdir(parents=True)  # Ctrl-C during the first step
    process(_config(cap, scene))
    assert (scene / "transforms.json").is_file()
    # an --overwrite run interrupted while building: its staging folder is removed next time
    staging = tmp_path / ".scene.edygs-staging"
    (staging / WORK_DIR_NAME).mkdir(parents=True)
    assert process(_config(cap, scene))["steps_reused"] == ["read", "edi", "poses", "write"]
    assert not staging.exists()
    # a swap interrupted after the old scene moved out: the old scene is put back
    before = (scene / "transforms.json").read_bytes()
    retired = tmp_path / ".scene.edygs-old"
    retired.mkdir()
    for name in ("transforms.json", STEP_RECORD_NAME):
        (scene / name).rename(retired / name)
    assert process(_config(cap, scene))["steps_reused"] == ["read", "edi", "poses", "write"]
    assert (scene / "transforms.json").read_bytes() == before and not retired.exists()


def test_changed_settings_redo_work_products_but_protect_a_scene(cap, tmp_path: Path, monkeypatch) -> None:
    static = write_tiny_capture(tmp_path / "static", n=4, shift_px=0)
    scene = tmp_path / "scene"
    colmap = replace(_config(static, scene), poses="colmap")
    with pytest.raises(motion_check.StaticCameraError):
        process(colmap)
    assert not (scene / "transforms.json").exists()
    # no scene there yet: other settings simply redo the work (no "would replace the processed scene")
    report = process(replace(colmap, poses="given", edi=EdiConfig(k=2)))
    assert report["steps_reused"] == [] and (scene / "transforms.json").is_file()
    with pytest.raises(FileExistsError, match=r"processed scene there was made from them\. Pass --overwrite .*stays"):
        process(replace(colmap, poses="given"))


def test_static_camera_is_caught_before_colmap(tmp_path: Path, monkeypatch) -> None:
    static = write_tiny_capture(tmp_path / "static", n=5, shift_px=0)

    def no_colmap(*args, **kwargs):
        raise AssertionError("COLMAP ran on a static camera")

    monkeypatch.setattr(pipeline_module, "run_colmap", no_colmap)
    config = replace(_config(static, tmp_path / "scene"), poses="colmap")
    with pytest.raises(motion_check.StaticCameraError, match=r"the camera does not move: .*--poses given --given-poses FILE"):
        process(config)


def test_motion_check_sees_a_moving_camera_and_skips_featureless_frames(tmp_path: Path) -> None:
    import cv2
    import numpy as np

    from capture_fixtures import textured_frames

    paths = []
    for i, frame in enumerate(textured_frames(4, (120, 160), shift_px=3)):
        paths.append(tmp_path / f"{i}.png")
        cv2.imwrite(str(paths[-1]), frame)
    assert motion_check.check_camera_moves(paths, 2.0) == pytest.approx(9.0, abs=1.0)
    assert motion_check.check_camera_moves(paths, 0.0) is None
    flat = [tmp_path / "flat0.png", tmp_path / "flat1.png"]
    for p in flat:
        cv2.imwrite(str(p), np.full((48, 64), 128, np.uint8))
    assert motion_check.check_camera_moves(flat, 2.0) is None
    rng = np.random.default_rng(0)
    noise = [tmp_path / f"noise{i}.png" for i in range(3)]
    for p in noise:  # unrelated frames (e.g. EDI latents of featureless frames): never "static"
        cv2.imwrite(str(p), rng.integers(0, 256, (48, 64)).astype(np.uint8))
    assert motion_check.check_camera_moves(noise, 2.0) == float("inf")


def test_first_frame_before_the_events_is_dropped_and_reported(tmp_path: Path) -> None:
    cap = write_tiny_capture(tmp_path / "raw", n=5, event_span_us=(30_000, 4 * PERIOD_US + EXPOSURE_US))
    report = process(_config(cap, tmp_path / "scene"))
    assert report["dropped_frames"] == [0] and report["n_blurry"] == 4
    assert any("dropped 1 of 5 frames" in note for note in report["notes"])


def test_entrypoint_errors_are_one_line(cap, tmp_path: Path, monkeypatch, capsys) -> None:
    argv = ["edygs-process", "--output", str(tmp_path / "scene"), "--exposures", str(cap.root / "missing.csv"),
            "--events", str(cap.events)]
    monkeypatch.setattr(sys, "argv", argv)
    with pytest.raises(SystemExit) as info:
        entrypoint()
    out = capsys.readouterr().out
    assert info.value.code == 1 and "Traceback" not in out
    failure = [line for line in out.splitlines() if "edygs-process failed" in line]
    assert len(failure) == 1 and failure[0].endswith("missing.csv: exposure table not found")
