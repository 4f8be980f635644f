"""Training configuration: pydantic models, one block per part, and presets stored as JSON data.

A preset is a JSON file in ``neudf_core/presets/`` holding any subset of the blocks below; what it leaves
out takes the defaults, which are the paper's. Overrides (from the CLI or a job) merge on top.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from neudf_core.renderer import SectionMode, VarsigmaKind, WeightMode

PRESET_DIR = Path(__file__).parent / "presets"


class _Block(BaseModel):
    model_config = ConfigDict(extra="forbid")


class FieldConfig(_Block):
    """The UDF network Psi (paper: 8x256, PE 6, skip at 4, weight norm, Softplus beta=100)."""

    d_hidden: int = 256
    n_layers: int = 8
    skip_in: tuple[int, ...] = (4,)
    n_freqs: int = 6
    d_feature: int = 256
    init_radius: float | None = Field(
        None, description="geometric init radius; None: chosen by the trainer: a sphere of radius 0.5 for the "
        "signed baseline and for a capture whose sparse points anchor nothing, else a point")
    use_weight_norm: bool = True
    output: Literal["softplus", "abs"] = Field(
        "softplus", description="Psi >= 0 from the last layer's h: Softplus(beta=100) (the paper) or |h| (sharp cusp)")
    encoding: Literal["frequency", "hashgrid"] = "frequency"
    hash_levels: int = 16
    hash_features: int = 2
    hash_log2_table: int = 19
    hash_base_res: int = 16
    hash_max_res: int = 2048
    gradient: Literal["autograd", "finite_difference"] = Field(
        "autograd", description="grad Psi by double backward (exact) or finite differences (no 2nd-order graph)")
    fd_eps: float = Field(1e-3, description="finite-difference step, about a cell of the finest hash level")


class ColorConfig(_Block):
    """The colour network (paper: 4x256, view-direction PE 4)."""

    d_hidden: int = 256
    n_layers: int = 4
    n_freqs_view: int = 4
    view_dependent: bool = Field(
        True, description="feed the view direction to the colour network (the paper); false keeps lids off openings")


class BackgroundConfig(_Block):
    """NeRF++ outside the unit sphere; none when masks are used or the background is a known colour."""

    d_hidden: int = 256
    n_layers: int = 8
    n_freqs: int = 10
    n_samples: int = 32
    view_dependent: bool = Field(True, description="colour depends on the view direction (NeRF++); False: "
                                 "the surroundings cannot paint the object behind it, view by view")
    floor: bool = Field(False, description="the floor the scene stage found is an opaque textured plane "
                        "inside the unit sphere: a ray that reaches it there takes its colour, so the floor and "
                        "the object's shadow on it are drawn where they are, not by the object or from beyond "
                        "the sphere")
    floor_freqs: int = Field(8, ge=0, description="frequencies of the floor texture's encoding of (x, z)")


class RendererConfig(_Block):
    """The rendering weight. ``weight`` picks NeUDF or one of the paper's baselines."""

    weight: WeightMode = "neudf"
    varsigma: VarsigmaKind = Field(
        "rational", description="CDF of the U-density: rational (the paper), exp (a shorter halo) or atan")
    sharpness_init: float = Field(0.05, description="r for NeUDF (paper: 0.05), s for the NeuS baselines")
    sharpness_floor_end: float = Field(
        0.0, description="not in the paper (0 = off, NeUDF only): floor on r, geometric from sharpness_init to this")
    sharpness_floor_mode: Literal["clamp", "lift"] = Field(
        "clamp", description="clamp: r is the floor while the learned r is below it, and the images cannot move "
        "it; lift: the learned r is raised to the floor after each step, so the images can make it sharper")
    section: SectionMode = "midpoint_gradient"
    receding_opacity: bool = Field(
        True, description="NeUDF: sections where Psi rises absorb too (the paper); false halves the silhouette halo")
    cos_anneal_iters: int = 10_000
    signed_until: float = Field(
        0.0, ge=0.0, lt=1.0, description="not in the paper (0 = off; NeUDF with field.output abs): the share "
        "of training in which h, the field before |.|, is rendered as a signed distance with NeuS's weight and "
        "its learned s, from a sphere; NeUDF's weight on Psi = |h| takes over after it and opens the surface")

    @model_validator(mode="after")
    def _receding_needs_gradient_sections(self) -> "RendererConfig":
        if not self.receding_opacity and self.section == "samples":
            raise ValueError("renderer.receding_opacity false needs section midpoint_gradient: with samples as "
                             "section ends a ray that crosses a surface between two samples only falls, then rises")
        return self


class SamplerConfig(_Block):
    """64 coarse + 2 rounds x 32 importance samples, s doubling per round."""

    n_coarse: int = 64
    n_importance: int = 64
    n_rounds: int = 2
    s0: float = Field(64.0, description="zeta_s sharpness of the first round (doubles each round)")


class LossConfig(_Block):
    eikonal_weight: float = 0.1
    eikonal_min_udf: float = Field(0.0, description="skip eikonal samples with Psi below this (the cusp)")
    mask_weight: float = 0.0
    zero_region_weight: float = Field(
        0.0, description="not in the paper (0 = off): penalise h below -zero_region_margin (Psi ~ 0 over a volume)")
    zero_region_margin: float = Field(0.03, description="depth of h (before the output activation) where it acts")
    zero_region_from: float = Field(
        0.0, ge=0.0, lt=1.0, description="the share of training before the zero-region term acts: a field "
        "started as a sphere (field.init_radius) first shrinks onto the object as a closed surface; when above 0, "
        "the term also waits for 100 iterations")
    point_prior_weight: float = Field(
        0.0, description="not in the paper (0 = off): penalise the object's opacity on rays that pass no sparse "
        "point of the object (DATA/object_points.npy), so the surroundings are not drawn inside the sphere")
    point_prior_radius: float = Field(
        0.06, gt=0, description="a ray passes a sparse point when it comes this close (unit sphere) in the image")
    point_surface_weight: float = Field(
        0.0, ge=0.0, description="not in the paper (0 = off): pull Psi towards 0 at the object's sparse points "
        "(DATA/object_points.npy), so the surface grows where features were triangulated, not only where the "
        "field's start puts it")
    point_surface_batch: int = Field(512, ge=1, description="sparse points drawn per iteration for that term")
    point_surface_until: float = Field(
        1.0, gt=0.0, le=1.0, description="the share of training over which that term fades linearly to 0: it "
        "places the surface early, and the colours alone shape it at the end (noisy points held to the end "
        "draw stacked sheets)")
    point_sight_weight: float = Field(
        0.0, ge=0.0, description="not in the paper (0 = off): keep the field's surface off the lines of sight from "
        "the frames that saw an anchor to just short of it (DATA/object_point_views.npy), so an anchor is met by "
        "the surface those frames see and not by a sheet hidden behind it; fades with point_surface_until")
    point_sight_margin: float = Field(
        0.01, gt=0.0, description="Psi below this on a line of sight is surface in the way (unit sphere); a "
        "frame whose line would pass real cloth that close (the anchor's own, seen obliquely, or other anchors) "
        "is not used for that anchor")
    point_sight_gap: float = Field(
        0.03, ge=0.0, description="how far short of the anchor a line of sight stops (the points' scatter)")
    point_sight_samples: int = Field(32, ge=1, description="points drawn on each line of sight")
    point_sight_clear: bool = Field(
        True, description="leave out the lines of sight that would pass real cloth within the margin (False: "
        "every frame that saw an anchor)")


class OptimConfig(_Block):
    lr: float = 2e-4
    lr_encoding: float | None = Field(None, description="learning rate of hash-grid tables (default: lr)")
    amp: bool = Field(False, description="bf16 autocast on CUDA (ignored on CPU)")
    lr_end_factor: float = 0.05
    warmup_iters: int = 5_000
    iters: int = 400_000
    rays: int = 512
    images_per_batch: int = 8
    object_rays: float = Field(0.0, ge=0, le=1, description="share of rays drawn where they meet the unit sphere")


class DataConfig(_Block):
    max_size: int = Field(0, description="downscale images to this longest side for training (0 = keep)")
    sphere_px: int = Field(0, ge=0, description="downscale images to about this many pixels across the unit sphere")
    floor_y: float | None = Field(None, description="height (y up) below which nothing is object, from region.json")
    use_masks: bool = False
    white_background: bool = False


class LogConfig(_Block):
    log_every: int = 100
    val_every: int = 5_000
    val_size: int = 128
    ckpt_every: int = 10_000


class TrainConfig(_Block):
    preset: str = "paper"
    seed: int = 0
    field: FieldConfig = FieldConfig()
    color: ColorConfig = ColorConfig()
    background: BackgroundConfig = BackgroundConfig()
    renderer: RendererConfig = RendererConfig()
    sampler: SamplerConfig = SamplerConfig()
    loss: LossConfig = LossConfig()
    optim: OptimConfig = OptimConfig()
    data: DataConfig = DataConfig()
    log: LogConfig = LogConfig()

    @model_validator(mode="after")
    def _signed_start_needs_abs(self) -> "TrainConfig":
        if self.renderer.signed_until > 0 and self.renderer.weight == "neudf" and self.field.output != "abs":
            raise ValueError("renderer.signed_until needs field.output abs: only |h| keeps the sign that the signed "
                             "start renders")
        return self


# Options that are gone, with the value the code now always uses: a run's config.json written before
# holds them; at that value they are dropped on loading, any other value is refused as an unknown key.
RETIRED = {
    "background": {"enabled": True},
    "renderer": {"normal_reg_k": 5},
    "sampler": {"importance_start_iter": 0},
    "loss": {"normal_smooth_weight": 0.0},
}


def load_saved_config(text: str) -> TrainConfig:
    """The configuration a run folder's config.json holds (the text), also one written before an option retired."""
    data = json.loads(text)
    for block, retired in RETIRED.items():
        section = data.get(block)
        if isinstance(section, dict):
            for key, value in retired.items():
                if key in section and section[key] == value:
                    del section[key]
    return TrainConfig.model_validate(data)


def available_presets() -> list[str]:
    return sorted(p.stem for p in PRESET_DIR.glob("*.json"))


# What a job trains with when the user names no preset: the same budget in minutes buys a larger model on a GPU.
DEVICE_PRESETS = {"cpu": "quick", "cuda": "gpu"}


def default_preset(device: str) -> str:
    """The preset for ``device`` ("cpu", "cuda", "cuda:N")."""
    return DEVICE_PRESETS["cuda" if device.startswith("cuda") else "cpu"]


def deep_merge(base: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in extra.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def load_config(preset: str = "paper", overrides: dict[str, Any] | None = None) -> TrainConfig:
    """The preset's values on top of the defaults, then ``overrides`` on top. Unknown keys are errors."""
    path = PRESET_DIR / f"{preset}.json"
    if not path.is_file():
        raise ValueError(f"unknown preset {preset!r}; available: {', '.join(available_presets())}")
    preset_data = {k: v for k, v in json.loads(path.read_text()).items() if not k.startswith("_")}
    data = deep_merge(preset_data, overrides or {})
    data["preset"] = preset
    return TrainConfig.model_validate(data)
