"""The EDyGS model: motion-mask Gaussians + deformation field + per-latent pose refinement.

The model renders, computes the losses and carries out the phase steps it is asked for
(``apply_phase``, ``enter_dynamic_phase``, ``refresh_motion``); the maths lives in ``losses/``,
``model/deformation.py``, ``model/appearance.py`` and the rasteriser backends; what trains when is
``model/phases.py``, and the training callbacks that drive the phases by step are
``training/phase_driver.py``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable, Dict, List, Literal, Optional, Tuple, Type, Union

import torch
from torch import Tensor
from torch.nn import Parameter
from tyro.conf import Suppress

from nerfstudio.cameras.cameras import Cameras
from nerfstudio.configs.config_utils import to_immutable_dict
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.models.base_model import ModelConfig
from nerfstudio.utils.rich_utils import CONSOLE

from edygs_ns.events.color import decode_to_linear
from edygs_ns.geometry import adjust_poses, c2w_opencv, viewmats_from_c2w
from edygs_ns.losses.blur import blur_loss
from edygs_ns.losses.events import DEFAULT_LOG_EPS, event_loss
from edygs_ns.losses.names import LossName
from edygs_ns.losses.photometric import l1_dssim, latent_confidence
from edygs_ns.losses.regularizers import mask_consistency, mask_l1, motion_loss
from edygs_ns.model.appearance import MAX_SH_DEGREE, sh_to_rgb
from edygs_ns.model.deformation import DeformationConfig, DeformationField, RigidMotion
from edygs_ns.model.exposure_cache import NO_EXPOSURE, ExposureCache
from edygs_ns.model.dynamic_seeding import (
    DynamicSeedingConfig,
    dilate,
    evidence_track,
    fit_motion,
    motion_evidence,
    seed_gaussians,
)
from edygs_ns.model.motion_init import MotionInit, initialise_motion
from edygs_ns.model.pose_refinement import PoseRefinementConfig, PoseRefiner
from edygs_ns.model.rigid_track import RigidTrackConfig
from edygs_ns.model.gaussians import GAUSSIAN_ATTRIBUTES, init_gaussians, seed_tensors
from edygs_ns.model.splat_export_view import SplatExportView
from edygs_ns.model.strategy import DensifyConfig, append_gaussians, make_strategy, strategy_info
from edygs_ns.render.contract import RasterOutputs, select_backend
from edygs_ns.model.phases import (
    CAMERA_GROUP,
    DEFORMATION_GROUP,
    MASK_GROUP,
    RIGID_GROUP,
    Phase,
    PhaseSchedule,
    is_active,
    is_trainable,
    phase_at,
)

#: smallest scale after adding the deformation's scale offset (world units).
MIN_DEFORMED_SCALE = 1e-6


@dataclass
class EdygsModelConfig(ModelConfig):
    """EDyGS: every knob of the model, the losses and the phase schedule. ``Suppress`` hides a field
    from ``ns-train --help`` and the command line (docs/method.md, "Configuration notes"); the first
    five are nerfstudio's NeRF settings, unused by a Gaussian model."""

    _target: Type = field(default_factory=lambda: EdygsModel)
    enable_collider: Suppress[bool] = True
    collider_params: Suppress[Optional[Dict[str, float]]] = to_immutable_dict({"near_plane": 2.0, "far_plane": 6.0})
    loss_coefficients: Suppress[Dict[str, float]] = to_immutable_dict({"rgb_loss_coarse": 1.0, "rgb_loss_fine": 1.0})
    eval_num_rays_per_chunk: Suppress[int] = 4096
    prompt: Suppress[Optional[str]] = None
    schedule: PhaseSchedule = field(default_factory=PhaseSchedule)
    """lengths of the pose-init and static phases (the dynamic phase runs to the end)"""
    deformation: DeformationConfig = field(default_factory=DeformationConfig)
    """shape of the deformation MLP"""
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    """densification / pruning rules (3DGS)"""
    seeding: DynamicSeedingConfig = field(default_factory=DynamicSeedingConfig)
    """motion evidence and dynamic seeds at the static -> dynamic switch"""
    rigid_track: RigidTrackConfig = field(default_factory=RigidTrackConfig)
    """rigid tracking of each moving object's seeds at the switch (its base motion afterwards)"""
    camera_optimizer: PoseRefinementConfig = field(default_factory=PoseRefinementConfig)
    """per-latent-frame pose refinement (nerfstudio's camera optimiser; rotation-step: D24)"""
    rasterizer: Literal["auto", "cpu", "torch", "gsplat"] = "auto"
    """rasteriser; auto: gsplat on CUDA, the compiled one on CPU"""
    sh_degree: int = 3
    """maximum spherical-harmonics degree"""
    sh_degree_interval: int = 1000
    """raise the SH degree by one every this many iterations"""
    init_opacity: float = 0.1
    """opacity of new Gaussians"""
    init_mask: float = 0.1
    """initial motion-mask value m of every Gaussian (biased towards static)"""
    num_random: Suppress[int] = 5000
    """Gaussians drawn uniformly in the scene box when the data has no points"""
    fallback_time: float = 0.0
    """time in [0, 1] for cameras without one; $EDYGS_TIME overrides it"""
    background_color: Literal["black", "white"] = "black"
    """background colour of renders (the motion mask's background is 0)"""
    ssim_lambda: float = 0.2
    """λ of L = (1 − λ) L1 + λ D-SSIM"""
    lambda_edi: float = 1.0
    """weight of L(Ĉ, EDI latent)"""
    lambda_edi_static: float = 1.0
    """weight of the static term L(Ĉ(1 − M), EDI(1 − M)) (static phase)"""
    edi_centre_weighting: float = 2.0
    """a: EDI latent at u ∈ [0, 1] of its exposure weighs ∝ 1 / (1 + a (2u − 1)²)"""
    lambda_blur: float = 24.0
    """weight of the blur-formation loss (not in the paper)"""
    lambda_event: float = 0.5
    """weight of the event loss between consecutive latent renders"""
    lambda_mask: float = 0.15
    """weight of ‖M‖₁ in the static phase, the bias towards static"""
    lambda_mask_consistency: float = 0.1
    """weight of ‖M − M̂‖₁ in the dynamic phase (M̂: seeding.consistency_target)"""
    lambda_motion: float = 0.1
    """weight of the motion loss ‖(1 − m)Δ‖² (dynamic phase)"""
    event_log_eps: Suppress[float] = DEFAULT_LOG_EPS
    """ε in ln(I + ε) of the event loss"""
    use_edi_loss: bool = True
    """ablation switch: supervise with the EDI latent images"""
    use_event_loss: bool = True
    """ablation switch: supervise with the events between consecutive latents"""
    use_blur_loss: bool = True
    """switch of the blur-formation loss (``lambda_blur``; not in the paper)"""
    optimize_poses: bool = True
    """ablation switch: refine the per-latent camera poses"""
    use_motion_mask: bool = True
    """ablation switch: the motion-mask field and its losses"""
    use_deformation: bool = True
    """ablation switch: the deformation field in the dynamic phase"""
    deform_mask_threshold: float = 0.2
    """deform only Gaussians with m >= this (0: all, as the paper)"""
    deform_subset: Literal["auto", "gather", "masked"] = "auto"
    """deform the subset gathered (host round trip) or all Gaussians masked; auto: masked on CUDA"""
    detach_mask_in_motion_loss: Suppress[bool] = True
    """no gradient from the motion loss into m (calling Gaussians dynamic cannot lower it)"""
    ablation: Optional[Literal["events-only", "edi-only", "edi-events", "edi-events-pose", "paper", "full", "blurry"]] = None
    """the switches above as a row of the paper's Table 2 (it sets them, over values given on the
    command line); None: as given"""

    def __post_init__(self) -> None:
        from edygs_ns.model.ablations import apply_ablation

        apply_ablation(self)


class EdygsModel(SplatExportView):
    """Motion-mask Gaussians with a deformation field, trained in three phases."""

    config: EdygsModelConfig

    def __init__(self, *args, seed_points: Optional[Tuple[Tensor, Tensor]] = None, **kwargs) -> None:
        self.seed_points = seed_points
        super().__init__(*args, **kwargs)

    # ------------------------------------------------------------------ set-up
    def populate_modules(self) -> None:
        if self.config.sh_degree > MAX_SH_DEGREE:
            raise ValueError(f"sh_degree must be <= {MAX_SH_DEGREE}, got {self.config.sh_degree}")
        metadata = self.kwargs.get("metadata", {}) or {}
        self.theta = float(metadata.get("theta", 0.2))
        self.color_space = str(metadata.get("color_space", "linear"))
        if self.seed_points is not None and len(self.seed_points[0]) > 0:
            points, colors = self.seed_points
        else:
            aabb = self.scene_box.aabb
            generator = torch.Generator().manual_seed(0)
            points = aabb[0] + (aabb[1] - aabb[0]) * torch.rand(self.config.num_random, 3, generator=generator)
            colors = None
        self.gauss_params = init_gaussians(
            points, colors, self.config.sh_degree, self.config.init_opacity, self.config.init_mask
        )
        self.deformation = DeformationField(self.config.deformation)
        # one rigid body per moving object, set from the rigid tracks at the dynamic switch
        self.rigid_motion = RigidMotion(self.num_train_data, bodies=self.config.seeding.max_objects)
        camera_config = self.config.camera_optimizer
        if not self.config.optimize_poses:
            camera_config = replace(camera_config, mode="off")
        self.camera_optimizer: PoseRefiner = camera_config.setup(num_cameras=self.num_train_data, device="cpu")
        latent_index = metadata.get("latent_index")
        if latent_index is None or len(latent_index) != self.num_train_data:
            latent_index = torch.full((self.num_train_data,), -1, dtype=torch.long)
        # per-training-image weight of the EDI terms (1 for images that are not EDI latents)
        self.register_buffer(
            "edi_weights", latent_confidence(latent_index, int(metadata.get("k", 1)), self.config.edi_centre_weighting), persistent=False
        )
        blurry_index = metadata.get("blurry_index")
        if blurry_index is None or len(blurry_index) != self.num_train_data:
            blurry_index = torch.full((self.num_train_data,), NO_EXPOSURE, dtype=torch.long)
        self.exposure_cache = ExposureCache(blurry_index)
        self.strategy = make_strategy(self.config.densify, blur_loss=self.config.use_blur_loss)
        self.strategy_state = self.strategy.initialize_state(scene_scale=1.0)
        # mask-consistency targets M̂ fixed at the dynamic switch, one per training latent [N, H, W]
        # (motion evidence near the movers, or the static model's rendered mask: seeding.consistency_target)
        self.register_buffer("static_masks", torch.zeros(0, 0, 0, dtype=torch.float16))
        # RGB + motion-mask channel behind the Gaussians [4], on the device (no upload per render)
        rgba = [1.0, 1.0, 1.0, 0.0] if self.config.background_color == "white" else [0.0, 0.0, 0.0, 0.0]
        self.register_buffer("background_rgba", torch.tensor(rgba), persistent=False)
        self.step = 0
        self.optimizers: Dict[str, torch.optim.Optimizer] = {}
        # densification statistics of the step's render, read by the strategy after backward (as in splatfacto)
        self._info: Optional[dict] = None
        self._train_cameras: Optional[Cameras] = None
        self._train_image: Optional[Callable[[int], Tensor]] = None  # set by bind_training_data
        self._train_size: Optional[Tuple[int, int]] = None  # (width, height) of every training latent

    @property
    def num_points(self) -> int:
        return int(self.gauss_params["means"].shape[0])

    @property
    def phase(self) -> Phase:
        return phase_at(self.step, self.config.schedule)

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        groups = {name: [self.gauss_params[name]] for name in GAUSSIAN_ATTRIBUTES}
        groups[DEFORMATION_GROUP] = list(self.deformation.parameters())
        groups[RIGID_GROUP] = list(self.rigid_motion.parameters())
        self.camera_optimizer.get_param_groups(param_groups=groups)
        return groups

    def load_state_dict(self, state_dict, strict: bool = True):  # type: ignore[override]
        """Resize Gaussians and the static-mask buffer to the checkpoint, keeping Parameter objects
        (the optimizers already hold them), then load."""
        for name in GAUSSIAN_ATTRIBUTES:
            key = f"gauss_params.{name}"
            if key in state_dict:
                param = self.gauss_params[name]
                param.data = torch.zeros(state_dict[key].shape, dtype=param.dtype, device=param.device)
        self.rigid_motion.prepare_load(state_dict, "rigid_motion.")
        self.deformation.prepare_load(state_dict, "deformation.")
        self.exposure_cache.prepare_load(state_dict, "exposure_cache.")
        self.camera_optimizer.prepare_load(state_dict, "camera_optimizer.")
        if "static_masks" in state_dict:
            self.static_masks = torch.zeros_like(state_dict["static_masks"], device=self.static_masks.device)
        return super().load_state_dict(state_dict, strict=strict)

    # ------------------------------------------------------------ training hooks
    def bind_training_data(self, cameras: Cameras, image: Callable[[int], Tensor]) -> None:
        """The training cameras (in training-index order) and a reader of training image i ([H, W, C]),
        which the phase switch, the evidence refresh and the exposure cache render against."""
        self._train_cameras = cameras
        self._train_image = image
        # read once here, so a training step does not read the cameras' size from the device
        widths, heights = cameras.width.reshape(-1), cameras.height.reshape(-1)
        same = len(widths) > 0 and bool((widths == widths[0]).all()) and bool((heights == heights[0]).all())
        self._train_size = (int(widths[0]), int(heights[0])) if same else None

    def get_training_callbacks(self, attrs: TrainingCallbackAttributes) -> List[TrainingCallback]:
        """The densification step after each iteration; the phases are driven by the pipeline's
        callbacks (training/phase_driver.py)."""
        select_backend(self.device, self.config.rasterizer)  # a missing CUDA build fails here, in one line
        return [TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self.after_step)]

    def begin_step(self, step: int, optimizers: Dict[str, torch.optim.Optimizer]) -> None:
        """Record the training step about to run and the optimizers (densification edits their state)."""
        self.step = step
        self.optimizers = optimizers

    @property
    def switched(self) -> bool:
        """Whether the static -> dynamic switch has happened (M̂ stored; kept in checkpoints)."""
        return self.static_masks.numel() > 0

    @property
    def seeding_active(self) -> bool:
        """Motion evidence, dynamic seeds and the time curriculum need the mask and the deformation."""
        return self.config.seeding.enabled and self.config.use_motion_mask and self.config.use_deformation

    def after_step(self, step: int) -> None:
        """Densification statistics of the step (on the device); on refinement steps (every
        refine_every) gsplat grows and prunes, which reads counts on the host: a rare sync."""
        if self._info is None:
            return
        self.strategy.step_post_backward(
            params=self.gauss_params, optimizers=self.optimizers, state=self.strategy_state, step=step,
            info=self._info, packed=False,
        )
        self._info = None

    def trainable_groups(self, phase: Phase) -> Dict[str, bool]:
        """Whether each parameter group trains in ``phase``, after the ablation switches."""
        switches = {
            MASK_GROUP: self.config.use_motion_mask,
            CAMERA_GROUP: self.config.optimize_poses,
            DEFORMATION_GROUP: self.config.use_deformation,
            RIGID_GROUP: self.config.use_deformation,
        }
        groups = list(GAUSSIAN_ATTRIBUTES) + [DEFORMATION_GROUP, RIGID_GROUP, CAMERA_GROUP]
        return {g: is_trainable(g, phase) and switches.get(g, True) for g in groups}

    def apply_phase(self, phase: Phase) -> None:
        """Set requires_grad of every parameter group for ``phase`` (frozen groups get no update)."""
        flags = self.trainable_groups(phase)
        for name in GAUSSIAN_ATTRIBUTES:
            self.gauss_params[name].requires_grad_(flags[name])
        for p in self.deformation.parameters():
            p.requires_grad_(flags[DEFORMATION_GROUP])
        for p in self.rigid_motion.parameters():
            p.requires_grad_(flags[RIGID_GROUP])
        for p in self.camera_optimizer.parameters():
            p.requires_grad_(flags[CAMERA_GROUP])

    @torch.no_grad()
    def _render_latents(self, deform: bool, with_evidence: bool) -> Dict[str, Tensor]:
        """Render every training latent at its refined pose: "mask" [N, H, W]; with_evidence also
        "rgb" [N, H, W, 3], "residual" |rgb − latent| [N, H, W], "depth" [N, H, W] (0 where the
        accumulation is below 0.5) and "c2w" [N, 3, 4] (nerfstudio axes)."""
        cameras = self._train_cameras.to(self.device)
        keys = ("mask", "rgb", "residual", "depth", "c2w") if with_evidence else ("mask",)
        stacks: Dict[str, List[Tensor]] = {k: [] for k in keys}
        for i in range(cameras.shape[0]):
            camera = cameras[i : i + 1]
            camera.metadata = {"cam_idx": i}
            out = self.render_cameras(camera, deform=deform)
            stacks["mask"].append(out["mask"][0, ..., 0])
            if with_evidence:
                image = self._train_image(i)[..., :3].to(self.device)
                stacks["rgb"].append(out["rgb"][0])
                stacks["residual"].append((out["rgb"][0] - image).abs().mean(dim=-1))
                depth = out["depth"][0, ..., 0]
                stacks["depth"].append(torch.where(out["accumulation"][0, ..., 0] > 0.5, depth, torch.zeros_like(depth)))
                stacks["c2w"].append(self.camera_to_worlds(camera)[0])
        return {k: torch.stack(v) for k, v in stacks.items()}

    def _latent_times(self) -> Tuple[Tensor, int]:
        """Normalised time of every training latent [N] and the index of the reference latent."""
        cameras = self._train_cameras
        times = cameras.times.reshape(-1).to(self.device) if cameras.times is not None else torch.zeros(cameras.shape[0], device=self.device)
        return times, int(torch.argmin((times - self.config.seeding.reference_time).abs()))

    def _latent_image(self, i: int) -> Tensor:
        """Training latent i, RGB [H, W, 3] in [0, 1]."""
        return self._train_image(i)[..., :3].to(self.device)

    def _find_motion(self, renders: Dict[str, Tensor], evidence: Tensor, **kwargs) -> MotionInit:
        """``initialise_motion`` on the latents' renders (keyword arguments passed on)."""
        times, ref = self._latent_times()
        return initialise_motion(
            evidence, renders["depth"], renders["rgb"], self._latent_image, viewmats_from_c2w(renders["c2w"]),
            c2w_opencv(renders["c2w"]), self._train_cameras.get_intrinsics_matrices().to(self.device), times, ref,
            select_backend(self.device, self.config.rasterizer), self.config.seeding, self.config.rigid_track, **kwargs,
        )

    def _fit_tracks_into_mlp(self, found: MotionInit) -> str:
        """With ``rigid_track.as_base_motion`` off: regress the MLP onto the movers' tracks."""
        movers = found.movers
        if not movers:
            return ""
        points = torch.cat([o.seeds.points for o in movers]).to(self.device)
        offsets = torch.cat([o.track.apply(o.seeds.points) - o.seeds.points for o in movers], dim=1)
        losses = fit_motion(self.deformation, points, self._latent_times()[0], offsets.to(points), self.config.seeding)
        return f", motion initialised (fit loss {losses[0]:.4f} -> {losses[-1]:.4f})" if losses else ""

    def _seed_translation_track(self, renders: Dict[str, Tensor], evidence: Tensor) -> str:
        """Without rigid tracking: seeds at the reference latent's evidence, the MLP regressed onto
        the evidence centroid's translation track."""
        cfg = self.config.seeding
        times, ref = self._latent_times()
        depth, c2w_cv = renders["depth"], c2w_opencv(renders["c2w"])
        Ks = self._train_cameras.get_intrinsics_matrices().to(self.device)
        seeds = seed_gaussians(evidence[ref], depth[ref], self._latent_image(ref), Ks[ref], c2w_cv[ref], cfg)
        points = seeds.points
        message = f", {len(points)} dynamic seeds"
        new = seed_tensors(points, seeds.colors, seeds.radii, self.config.sh_degree, cfg.seed_opacity, cfg.seed_mask)
        added = append_gaussians(self.gauss_params, self.optimizers, self.strategy_state, new)
        track_idx, track_points = evidence_track(evidence, depth, Ks, c2w_cv, cfg)
        if added and ref in track_idx.tolist():
            offsets = track_points.to(points) - track_points[track_idx.tolist().index(ref)].to(points)
            message += f"; translation track on {len(track_idx)} latents"
            losses = fit_motion(self.deformation, points, times[track_idx.to(times.device)], offsets, cfg)
            if losses:
                message += f", motion initialised (fit loss {losses[0]:.4f} -> {losses[-1]:.4f})"
        return message

    def _add_movers(self, found: MotionInit, first_body: int) -> str:
        """Seed the movers of ``found`` and give each a rigid body from ``first_body`` on; returns the log lines."""
        seeds = found.seed_tensors()
        cfg = self.config.seeding
        message = ""
        times = self._latent_times()[0]
        for j, obj in enumerate(found.movers):
            message += f"\n  object {first_body + j}: {obj.summary()}"
            if self.config.rigid_track.as_base_motion:
                self.rigid_motion.set(obj.track.centre, obj.reach, obj.size, times, obj.track.rotvecs,
                                      obj.track.translations, body=first_body + j)
        for obj in found.objects:
            if not obj.moved:
                message += f"\n  no mover (no seeds): {obj.summary()}"
        new = seed_tensors(seeds.points.to(self.device), seeds.colors.to(self.device), seeds.radii.to(self.device),
                           self.config.sh_degree, cfg.seed_opacity, cfg.seed_mask)
        append_gaussians(self.gauss_params, self.optimizers, self.strategy_state, new)
        return message

    @property
    def body_count(self) -> int:
        """Rigid bodies set so far (movers found at the switch and at the refresh)."""
        return int((self.rigid_motion.reach > 0).sum())

    @torch.no_grad()
    def enter_dynamic_phase(self) -> None:
        """At the static -> dynamic switch: render every training latent with the static model at
        the refined poses and store the mask-consistency targets M̂; with seeding on, derive motion
        evidence, find the moving objects, seed and track each (model/motion_init.py)."""
        if self._train_cameras is None:
            return
        started = time.perf_counter()
        use_evidence = self.seeding_active and self._train_image is not None
        renders = self._render_latents(deform=False, with_evidence=use_evidence)
        rendered = renders["mask"]
        message = f"[edygs] dynamic phase from step {self.step}: {len(rendered)} mask-consistency targets"
        if not use_evidence:
            self.static_masks = rendered.half()
            CONSOLE.log(message + " (rendered static-phase masks)")
            return
        cfg = self.config.seeding
        found_evidence = motion_evidence(renders["residual"], cfg)
        evidence = found_evidence.mask
        targets = {"evidence": evidence, "rendered": rendered, "max": torch.maximum(rendered, evidence)}
        self.static_masks = targets[cfg.consistency_target].half()
        message += f" ({cfg.consistency_target}); {found_evidence.summary()}"
        if self.config.rigid_track.enabled:
            found = self._find_motion(renders, evidence)
            if cfg.consistency_target == "evidence":
                self.static_masks = found.consistency.half()
            before = self.num_points
            message += f"; {len(found.movers)} moving object(s) of {len(found.objects)} tracked region(s)"
            message += self._add_movers(found, first_body=0) + f"\n  {self.num_points - before} dynamic seeds"
            if not self.config.rigid_track.as_base_motion:
                message += self._fit_tracks_into_mlp(found)
        else:
            message += self._seed_translation_track(renders, evidence)
        CONSOLE.log(message + f"\n  (switch took {time.perf_counter() - started:.1f} s)")

    @torch.no_grad()
    def refresh_motion(self) -> None:
        """Find the motion evidence once more, on the dynamic model: a moving object the switch missed
        (too faint then, or hidden by the static model's errors) still leaves evidence that nothing
        dynamic explains. Such evidence, away from the rendered mask and from M̂, is tracked as at
        the switch; its movers get seeds, a rigid body and their evidence in M̂."""
        if self._train_cameras is None or self._train_image is None or not self.config.rigid_track.enabled:
            return
        if not self.config.rigid_track.as_base_motion or not self.switched:
            return
        started = time.perf_counter()
        cfg = self.config.seeding
        existing = self.body_count
        if existing >= cfg.max_objects:
            CONSOLE.log(f"[edygs] evidence refresh at step {self.step}: skipped, all {cfg.max_objects} rigid bodies in use")
            return
        renders = self._render_latents(deform=True, with_evidence=True)
        found_evidence = motion_evidence(renders["residual"], cfg)
        evidence = found_evidence.mask
        known = (renders["mask"] > 0.5) | (self.static_masks.to(self.device).float() > 0.5)
        margin = max(1, int(round(cfg.refresh_margin * known.shape[-1])))
        covered = dilate(known, margin)
        found = self._find_motion(renders, evidence, covered=covered, existing=existing, candidates=cfg.refresh_candidates,
                                  steady=False)
        before = self.num_points
        message = (f"[edygs] evidence refresh at step {self.step}: {found_evidence.summary()}, "
                   f"{100.0 * float((evidence.bool() & ~covered).float().mean()):.2f}% unexplained; "
                   f"{len(found.movers)} new moving object(s) of {len(found.objects)} tracked region(s)")
        if found.movers:
            message += self._add_movers(found, first_body=existing)
            self.static_masks = torch.maximum(self.static_masks, found.consistency.to(self.static_masks))
        else:
            message += "".join(f"\n  no mover (no seeds): {o.summary()}" for o in found.objects)
        CONSOLE.log(message + f"\n  {self.num_points - before} dynamic seeds (refresh took {time.perf_counter() - started:.1f} s)")

    # ------------------------------------------------------------ rendering
    def camera_indices(self, camera: Cameras) -> Optional[Tensor]:
        """Training-camera index of each camera [C] (on the device the metadata holds them on), or
        None (viewer / eval cameras)."""
        if camera.metadata is None or "cam_idx" not in camera.metadata:
            return None
        return torch.as_tensor(camera.metadata["cam_idx"], dtype=torch.long).reshape(-1)

    def image_size(self, camera: Cameras) -> Tuple[int, int]:
        """(width, height) in pixels of ``camera``'s images: for training latents while training,
        the size read at bind time; otherwise read from the camera (a host read on CUDA)."""
        if self.training and self._train_size is not None and camera.metadata and "cam_idx" in camera.metadata:
            return self._train_size
        return int(camera.width[0, 0]), int(camera.height[0, 0])

    def intrinsics(self, camera: Cameras) -> Tensor:
        """[C, 3, 3] pixel intrinsics on the model's device, made from the camera's fx, fy, cx, cy
        where they are (nerfstudio's ``get_intrinsics_matrices`` fills a host tensor)."""
        fx, fy, cx, cy = (getattr(camera, name).reshape(-1).to(self.device) for name in ("fx", "fy", "cx", "cy"))
        zero, one = torch.zeros_like(fx), torch.ones_like(fx)
        return torch.stack([fx, zero, cx, zero, fy, cy, zero, zero, one], dim=-1).reshape(-1, 3, 3).float()

    def masked_deformation(self) -> bool:
        """Whether the deformation runs on every Gaussian, masked (config.deform_subset)."""
        choice = self.config.deform_subset
        return choice == "masked" or (choice == "auto" and self.device.type == "cuda")

    def camera_to_worlds(self, camera: Cameras) -> Tensor:
        """[C, 3, 4] poses the model renders with: refined for training latents while training, as given otherwise."""
        return self.refined_camera_to_worlds(camera) if self.training else camera.camera_to_worlds

    def refined_camera_to_worlds(self, camera: Cameras) -> Tensor:
        """[C, 3, 4] poses after pose refinement, for cameras that carry ``metadata["cam_idx"]``
        (training latents); other cameras, or no refinement, give the poses unchanged."""
        c2w = camera.camera_to_worlds
        indices = self.camera_indices(camera)
        if indices is None or self.config.camera_optimizer.mode == "off" or not self.config.optimize_poses:
            return c2w
        return adjust_poses(c2w, self.camera_optimizer(indices).to(c2w.device))

    def gate_subset(self, mask: Tensor) -> Tensor:
        """Indices [S] of the Gaussians the gathered deformation moves: m >= deform_mask_threshold
        (every Gaussian when the gate is off). ``mask``: [N] motion-mask values. S is read on the
        host (``nonzero``): one sync per call on CUDA."""
        if self._gated():
            return torch.nonzero(self.gate(mask)).squeeze(-1)
        return torch.arange(mask.shape[0], device=mask.device)

    def _gated(self) -> bool:
        return self.config.use_motion_mask and self.config.deform_mask_threshold > 0

    def gate(self, mask: Tensor) -> Tensor:
        """bool [N]: the Gaussians the deformation may move, m >= deform_mask_threshold (all when
        the gate is off). ``mask``: [N] motion-mask values."""
        if self._gated():
            return mask.detach() >= self.config.deform_mask_threshold
        return torch.ones_like(mask, dtype=torch.bool)

    def _offsets(
        self, means: Tensor, quats: Tensor, time: Union[float, Tensor]
    ) -> Tuple[Tensor, Tensor, Tensor, Optional[Tensor]]:
        """Offsets (Δμ [S,3], Δq [S,4], Δs [S,3], Δrgb [S,3] or None) of the Gaussians given: the
        deformation MLP plus the rigid bodies' motion when some body moves (a host flag,
        model/deformation.py)."""
        d_xyz, d_rot, d_scale, d_colour = self.deformation.offsets(means, time)
        if self.rigid_motion.active:
            rigid_xyz, rigid_rot = self.rigid_motion(means, quats, time)
            d_xyz, d_rot = d_xyz + rigid_xyz, d_rot + rigid_rot
        return d_xyz, d_rot, d_scale, d_colour

    def deformed_gaussians(
        self, time: Union[float, Tensor], deform: bool, subset: Optional[Tensor] = None
    ) -> Dict[str, Tensor]:
        """Activated Gaussians at ``time`` (normalised; a float or a one-element tensor on the
        device): means [N,3], quats [N,4], scales [N,3], opacities [N], mask [N]; plus the offsets
        d_* of the deformed subset and its mask values for the motion loss. ``subset``: the
        gathered deformation's :meth:`gate_subset`, when the caller has it (None: computed here).
        With the masked deformation (:meth:`masked_deformation`) the offsets cover all N
        Gaussians, zero outside the subset, and "deformed_weight" [N] is 1 in the subset, 0
        elsewhere."""
        params = self.gauss_params
        means = params["means"]
        quats = torch.nn.functional.normalize(params["quats"], dim=-1)
        scales = torch.exp(params["scales"])
        mask = torch.sigmoid(params["mask_logit"]).squeeze(-1)
        if not self.config.use_motion_mask:
            mask = torch.zeros_like(mask)
        out = {"means": means, "quats": quats, "scales": scales, "opacities": torch.sigmoid(params["opacities"]).squeeze(-1), "mask": mask}
        if not deform:
            return out
        if self.masked_deformation():
            return self._deform_masked(out, time)
        if subset is None:
            subset = self.gate_subset(mask)
        d_xyz, d_rot, d_scale, d_colour = self._offsets(means[subset], quats[subset], time)
        if d_colour is not None:
            out["d_colour"] = torch.zeros_like(means).index_add(0, subset, d_colour)
        out["means"] = means.index_add(0, subset, d_xyz)
        out["quats"] = quats.index_add(0, subset, d_rot)
        out["scales"] = scales.index_add(0, subset, d_scale).clamp_min(MIN_DEFORMED_SCALE)
        out.update(d_xyz=d_xyz, d_rot=d_rot, d_scale=d_scale, deformed_mask=mask[subset])
        return out

    def _deform_masked(self, out: Dict[str, Tensor], time: Union[float, Tensor]) -> Dict[str, Tensor]:
        """The deformation of ``deformed_gaussians`` on every Gaussian, offsets kept where m >=
        deform_mask_threshold: the same result without the subset's size on the host."""
        means, quats, scales, mask = out["means"], out["quats"], out["scales"], out["mask"]
        selected = self.gate(mask)  # [N]
        d_xyz, d_rot, d_scale, d_colour = self._offsets(means, quats, time)
        keep = selected[:, None]

        def kept(d: Tensor) -> Tensor:
            return torch.where(keep, d, torch.zeros_like(d))

        d_xyz, d_rot, d_scale = kept(d_xyz), kept(d_rot), kept(d_scale)
        if d_colour is not None:
            out["d_colour"] = kept(d_colour)
        out["means"], out["quats"] = means + d_xyz, quats + d_rot
        out["scales"] = (scales + d_scale).clamp_min(MIN_DEFORMED_SCALE)
        out.update(d_xyz=d_xyz, d_rot=d_rot, d_scale=d_scale, deformed_mask=mask, deformed_weight=selected.to(mask.dtype))
        return out

    @staticmethod
    def _colours(coeffs: Tensor, gaussians: Dict[str, Tensor], camera_center: Tensor, sh_degree: int) -> Tensor:
        """[N, 3] colours seen from ``camera_center``: the SH colour plus the deformation's RGB offset
        where it has one."""
        rgb = sh_to_rgb(coeffs, gaussians["means"], camera_center, sh_degree)
        d_colour = gaussians.get("d_colour")
        return rgb if d_colour is None else rgb + d_colour

    def render_cameras(self, camera: Cameras, deform: Optional[bool] = None) -> Dict[str, Tensor]:
        """Render C cameras in one rasteriser call; every output has a leading camera dimension
        [C, H, W, ·], except "deform_terms": per camera, the deformed subset's offsets and mask
        values (the motion loss's input; empty when nothing deforms).

        A training step reads nothing back to the host here: the cameras' times stay on the
        device, the image size of training latents is read at bind time, and the Gaussians of the
        C cameras (deformed at each camera's time) go to the backend as [C, N, ·]."""
        if deform is None:
            # the deformation heads start at zero, so evaluating it before training is the identity
            deform = self.config.use_deformation and (self.phase is Phase.DYNAMIC or not self.training)
        backend = select_backend(self.device, self.config.rasterizer)
        c2w = self.camera_to_worlds(camera)
        viewmats = viewmats_from_c2w(c2w)
        Ks = self.intrinsics(camera)
        width, height = self.image_size(camera)
        n_cams = camera.shape[0]
        times: List[Union[float, Tensor]] = (
            list(camera.times.reshape(-1).unbind()) if camera.times is not None else [self.fallback_time] * n_cams
        )
        sh_degree = min(self.step // self.config.sh_degree_interval, self.config.sh_degree) if self.training else self.config.sh_degree
        coeffs = torch.cat([self.gauss_params["features_dc"][:, None], self.gauss_params["features_rest"]], dim=1)
        background = self.background_rgba.to(self.device)
        subset = None
        if deform and n_cams > 1 and not self.masked_deformation():
            # the gate depends on the mask alone, not on the time: one host read for the C cameras
            subset = self.gate_subset(torch.sigmoid(self.gauss_params["mask_logit"]).squeeze(-1))
        gaussians = [self.deformed_gaussians(times[c], deform, subset) for c in range(n_cams)]
        features = torch.stack([
            torch.cat([self._colours(coeffs, g, c2w[c, :3, 3], sh_degree), g["mask"][:, None]], dim=-1)
            for c, g in enumerate(gaussians)
        ])  # [C, N, D]: the view-dependent colour and the motion mask
        if n_cams == 1 or not deform:  # one set of Gaussians for every camera
            geometry = [gaussians[0][k] for k in ("means", "quats", "scales")]
            features = features[0] if n_cams == 1 else features
        else:
            geometry = [torch.stack([g[k] for g in gaussians]) for k in ("means", "quats", "scales")]
        out: RasterOutputs = backend(
            *geometry, gaussians[0]["opacities"], features, viewmats, Ks, width, height,
            backgrounds=background[None].expand(n_cams, -1),
        )
        if self.training and torch.is_grad_enabled() and self.gauss_params["means"].requires_grad:
            # densification statistics from the first camera, as when the cameras rendered one by one
            self._info = strategy_info(out, width, height, counted_cameras=1)
            self.strategy.step_pre_backward(self.gauss_params, self.optimizers, self.strategy_state, self.step, self._info)
        stacked: Dict[str, Union[Tensor, List]] = {
            "rgb": out.render[..., :3].clamp(0.0, 1.0), "mask": out.render[..., 3:4], "depth": out.depth,
            "accumulation": out.alpha,
        }
        stacked["rgb_static"] = stacked["rgb"] * (1.0 - stacked["mask"])
        keys = ("d_xyz", "d_rot", "d_scale", "deformed_mask", "deformed_weight")
        stacked["deform_terms"] = [{k: g[k] for k in keys if k in g} for g in gaussians if "d_xyz" in g]
        return stacked  # type: ignore[return-value]

    def get_outputs(self, camera: Cameras) -> Dict[str, Union[Tensor, List]]:  # type: ignore[override]
        """rgb, mask (motion mask M), rgb_static = rgb·(1 − M), depth, accumulation; [H, W, ·] for one
        camera, [C, H, W, ·] for several (training pairs)."""
        if not isinstance(camera, Cameras):
            raise ValueError("EdygsModel.get_outputs needs a Cameras object")
        outputs = self.render_cameras(camera)
        deform_terms = outputs.pop("deform_terms")
        if camera.shape[0] == 1:
            outputs = {k: v[0] for k, v in outputs.items()}
        if self.training:
            outputs["deform_terms"] = deform_terms  # read by get_loss_dict; the viewer lists only images
        background = torch.ones(3, device=self.device) if self.config.background_color == "white" else torch.zeros(3, device=self.device)
        if camera.shape[0] == 1 and not self.training:
            # the viewer lists every output as an image: give the background one too
            background = background.expand(*outputs["rgb"].shape[:2], 3)
        outputs["background"] = background
        return outputs  # type: ignore[return-value]

    @torch.no_grad()
    def get_outputs_for_camera(self, camera: Cameras, obb_box=None) -> Dict[str, Tensor]:  # type: ignore[override]
        return self.get_outputs(camera.to(self.device))  # type: ignore[return-value]

    # ---------------------------------------------------------------- losses
    @staticmethod
    def _as_float_image(image: Tensor, device: torch.device) -> Tensor:
        image = image.to(device)
        return image.float() / 255.0 if image.dtype == torch.uint8 else image.float()

    def get_metrics_dict(self, outputs, batch) -> Dict[str, Tensor]:
        gt = self._as_float_image(batch["image"], self.device)[..., :3]
        pred = outputs["rgb"]
        mse = (pred - gt.reshape(pred.shape)).square().mean()
        # host numbers as CPU scalars, the rest stays on the device: read only when logged
        metrics = {"psnr": -10.0 * torch.log10(mse.clamp_min(1e-10)), "gaussian_count": torch.full((), float(self.num_points))}
        metrics["phase"] = torch.full((), float(list(Phase).index(self.phase)))
        self._camera_metrics(metrics)
        return metrics

    def _camera_metrics(self, metrics: Dict[str, Tensor]) -> None:
        """The pose-refinement metrics of nerfstudio's ``CameraOptimizer.get_metrics_dict`` (same
        names; translations in world units, rotations in degrees), computed on the device (its own
        copies the rotations to the host every step)."""
        if self.camera_optimizer.config.mode == "off":
            return
        adjustment = self.camera_optimizer.adjustment().detach()
        trans, rot = adjustment[:, :3].norm(dim=-1), adjustment[:, 3:].norm(dim=-1)
        metrics["camera_opt_translation_max"] = trans.max()
        metrics["camera_opt_translation_mean"] = trans.mean()
        metrics["camera_opt_rotation_mean"] = torch.rad2deg(rot.mean())
        metrics["camera_opt_rotation_max"] = torch.rad2deg(rot.max())

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, Tensor]:
        cfg = self.config
        phase = self.phase if self.training else Phase.DYNAMIC
        rgb, mask = outputs["rgb"], outputs["mask"]
        gt = self._as_float_image(batch["image"], self.device)[..., :3].reshape(rgb.shape)
        losses: Dict[str, Tensor] = {}
        indices = self._batch_indices(batch, rgb) if self.training else None
        weights = None if indices is None or cfg.edi_centre_weighting == 0 else self.edi_weights[indices.to(self.edi_weights.device)]
        if cfg.use_edi_loss and is_active(LossName.EDI, phase):
            losses["edi"] = cfg.lambda_edi * l1_dssim(rgb, gt, cfg.ssim_lambda, image_weights=weights)
        if cfg.use_edi_loss and cfg.use_motion_mask and is_active(LossName.EDI_STATIC, phase):
            losses["edi_static"] = cfg.lambda_edi_static * l1_dssim(rgb, gt, cfg.ssim_lambda, weight=1.0 - mask, image_weights=weights)
        linear = decode_to_linear(rgb, self.color_space)
        pair = indices is not None and len(indices) == 2  # the two latents an event map joins
        if cfg.use_event_loss and is_active(LossName.EVENT, phase) and "event_map" in batch and pair:
            event_map = batch["event_map"].to(self.device).float()
            losses["event"] = cfg.lambda_event * event_loss(linear[0], linear[1], event_map, self.theta, cfg.event_log_eps)
        if cfg.use_blur_loss and cfg.lambda_blur > 0 and is_active(LossName.BLUR, phase) and "blurry" in batch and indices is not None:
            losses["blur"] = cfg.lambda_blur * self._blur_term(linear, indices, batch["blurry"])
        if cfg.use_motion_mask and is_active(LossName.MASK_L1, phase):
            losses["mask_l1"] = cfg.lambda_mask * mask_l1(mask)
        if cfg.use_motion_mask and is_active(LossName.MASK_CONSISTENCY, phase) and self.switched:
            if indices is not None:
                reference = self.static_masks[indices.to(self.static_masks.device)].to(self.device).float()[..., None]
                losses["mask_consistency"] = cfg.lambda_mask_consistency * mask_consistency(mask.reshape(reference.shape), reference)
        if cfg.use_motion_mask and is_active(LossName.MOTION, phase) and outputs.get("deform_terms"):
            terms = []
            for t in outputs["deform_terms"]:
                m = t["deformed_mask"].detach() if cfg.detach_mask_in_motion_loss else t["deformed_mask"]
                terms.append(motion_loss(t["d_xyz"], t["d_rot"], t["d_scale"], m, weight=t.get("deformed_weight")))
            losses["motion"] = cfg.lambda_motion * torch.stack(terms).mean()
        if self.training:
            self.camera_optimizer.get_loss_dict(losses)
        if not losses:
            # a phase with no active term (e.g. an ablation) still needs a differentiable zero
            losses["none"] = rgb.sum() * 0.0
        return losses

    def _blur_term(self, linear: Tensor, indices: Tensor, blurry: Tensor) -> Tensor:
        """Blur loss of the batch's exposure (renders in linear intensity; a training batch holds
        latents of one exposure), completed from the render cache (which it updates) on the device."""
        cache = self.exposure_cache
        if not cache.filled:  # once per run (or after a resume from a checkpoint without the cache)
            if self._train_image is None:
                raise RuntimeError("the blur loss needs the training images (bind_training_data)")
            cache.fill(lambda i: decode_to_linear(self._train_image(i)[..., :3].to(self.device), self.color_space))
        stack, weights = cache.complete_on_device(indices, linear)
        cache.store(indices, linear)
        target = decode_to_linear(blurry.to(self.device).float().reshape(-1, *linear.shape[-3:]), self.color_space)
        if target.shape[0] != 1:
            raise ValueError(f"the batch has {target.shape[0]} blurry frames for the 1 exposure of a training batch")
        return blur_loss(stack, target, weights)

    def _batch_indices(self, batch, rgb: Tensor) -> Optional[Tensor]:
        if "image_idx" not in batch:
            return None
        idx = torch.as_tensor(batch["image_idx"], dtype=torch.long).reshape(-1)
        expected = rgb.shape[0] if rgb.dim() == 4 else 1
        return idx if len(idx) == expected else None

    # ------------------------------------------------------------ evaluation
    def get_image_metrics_and_images(self, outputs, batch) -> Tuple[Dict[str, float], Dict[str, Tensor]]:
        from edygs_ns.losses.metrics import mask_iou, psnr, ssim

        gt = self._as_float_image(batch["image"], self.device)[..., :3]
        pred = outputs["rgb"]
        metrics = {"psnr": float(psnr(pred, gt)), "ssim": float(ssim(pred, gt))}
        if "motion_mask" in batch:
            metrics["mask_iou"] = float(mask_iou(outputs["mask"][..., 0], batch["motion_mask"].to(self.device)[..., 0] > 0.5))
        images = {"img": torch.cat([gt, pred], dim=1), "mask": outputs["mask"].repeat(1, 1, 3)}
        return metrics, images

