"""Meshing a trained run folder: load the model, extract the open mesh, keep what the cameras see,
colour the vertices and write the file (``neudf mesh``, the worker's mesh stage)."""

from __future__ import annotations

from pathlib import Path

import torch
import trimesh

from neudf_core.dataset import FLOOR_SHADOW_BAND, image_paths, load_cameras
from neudf_core.decimate import decimate
from neudf_core.export import SUFFIXES, export_mesh
from neudf_core.meshing import (
    UNIT_BOUNDS, Method, NoSurfaceError, NothingSeenError, color_vertices, cull_unseen, drop_small_components,
    evaluate_field, extract_mesh,
)
from neudf_core.meshing.cleanup import (drop_floor_pieces, fill_small_holes, keep_above, keep_in_sphere,
                                        trim_floor_skirt)
from neudf_core.meshing.lids import SPREAD_LID, open_lids
from neudf_core.numerics import flush_denormals
from neudf_core.progress import ProgressFn, null_progress, sub_progress
from neudf_core.texture import bake_texture
from neudf_core.trainer import load_model

# Pieces resting on the floor cut and lower than this (unit sphere) are floor and shadow, not object: the
# sheet learned over the floor of a garment video rose 0.10 above the cut; an object standing there rises higher.
FLOOR_BAND = 0.15
# Faces this low over the cut (unit sphere) and outside the footprint of the object SKIRT_ABOVE higher, grown
# by SKIRT_MARGIN, are a shadow fused to a standing object's foot.
SKIRT_BAND, SKIRT_ABOVE, SKIRT_MARGIN = FLOOR_SHADOW_BAND, 0.1, 0.03
# Separate pieces wholly beyond this radius are dropped: the capture fits the object within 0.7 of the unit
# sphere (scene's object_fill), clean renders within 0.8.
SPHERE_RIM = 0.85


def mesh_run(
    run_dir: str | Path,
    out_path: str | Path,
    *,
    method: Method | None = None,
    resolution: int = 256,
    threshold: float | None = None,
    min_component_faces: int = 32,
    min_component_fraction: float = 0.01,
    views: str | Path | None = None,
    min_seen_fraction: float = 0.15,
    lid_spread: float = SPREAD_LID,
    faces: int = 0,
    texture_size: int = 0,
    device: str = "cpu",
    progress: ProgressFn = null_progress,
) -> trimesh.Trimesh:
    """Mesh a trained run: UDF in the unit sphere's bounding box, vertex colours, exported to ``out_path``.

    The suffix of ``out_path`` picks the format (.glb, .ply, .obj); raises ValueError for others before
    the long work starts and for a method that does not fit the field (mc for NeuS-SDF runs, meshudf or
    spsr for unsigned ones); :class:`NoSurfaceError` when the field has no surface yet. Options as
    :func:`extract_mesh`.
    ``views``: the run's dataset folder; faces that fewer than ``min_seen_fraction`` of its cameras see
    are dropped (:func:`cull_unseen`; 0.15 is 8 of 48 views, where culling a tube's and a pants' inner
    sheets stopped gaining); :class:`NothingSeenError` when that leaves no face. Then patches the frames
    disagree on the colour of by more than ``lid_spread`` (default :data:`SPREAD_LID`; 0 keeps them) are
    cut as lids over openings (:func:`open_lids`).
    ``faces`` > 0: decimated to about that many faces (:func:`decimate`); ``texture_size`` > 0 (needs
    ``views``): a texture of that side baked from the dataset's frames (:func:`bake_texture`), and the
    returned mesh is the textured, two-sided one.
    """
    if texture_size > 0 and views is None:
        raise ValueError("a texture is baked from the frames: give the run's dataset folder (views)")
    if Path(out_path).suffix.lower() not in SUFFIXES:
        raise ValueError(f"unknown mesh format {Path(out_path).suffix!r}: use one of {', '.join(SUFFIXES)}")
    report = sub_progress(progress, 0.0, 0.6) if texture_size > 0 else progress  # the bake takes the rest
    flush_denormals()
    model = load_model(run_dir, device)
    model.eval()
    signed = bool(getattr(model, "signed", False))
    method = method or ("mc" if signed else "meshudf")
    cameras = load_cameras(views) if views is not None else None  # bad folders fail before the long work
    if signed and method != "mc":
        raise ValueError(f"{run_dir} learned a signed field (the NeuS-SDF baseline): mesh it with method mc")
    if not signed and method == "mc":
        raise ValueError(f"{run_dir} learned an unsigned field: mc needs a sign, use meshudf or spsr")

    def grad_fn(x: torch.Tensor) -> torch.Tensor:
        return model.udf_and_grad(x)[1]

    mesh = extract_mesh(
        model.udf, method=method, resolution=resolution, bounds=UNIT_BOUNDS, threshold=threshold,
        grad_fn=grad_fn, min_component_faces=min_component_faces, min_component_fraction=min_component_fraction,
        device=device, progress=sub_progress(report, 0.0, 0.85),
    )
    mesh = keep_in_sphere(mesh, SPHERE_RIM)
    if len(mesh.faces) == 0:
        raise NoSurfaceError("the field's surface lies wholly outside the unit sphere, where training renders "
                             "nothing of the object")
    floor_y = model.cfg.data.floor_y
    if floor_y is not None:  # training rendered nothing of the object below the floor: what is there is a guess
        mesh = keep_above(mesh, floor_y)
        mesh = drop_floor_pieces(mesh, floor_y, FLOOR_BAND, touch=2.0 * mesh.metadata["meshing"]["voxel"])
        mesh = trim_floor_skirt(mesh, floor_y, SKIRT_BAND, SKIRT_ABOVE, SKIRT_MARGIN)
        if len(mesh.faces) == 0:
            raise NoSurfaceError(f"the field's surface lies wholly below the floor found at height {floor_y:.3g} "
                                 "of the unit sphere: nothing of the object is above it")
    if cameras is not None:
        report(0.85, "dropping what no camera sees")
        info = mesh.metadata["meshing"]
        faces_before = len(mesh.faces)
        mesh = cull_unseen(mesh, cameras, min_seen_fraction, tol=2.0 * info["voxel"])
        mesh = open_lids(mesh, cameras, image_paths(Path(views)), tol=2.0 * info["voxel"], voxel=info["voxel"],
                         lid=lid_spread)
        lids = mesh.metadata.get("meshing", {}).get("faces_lids", 0)
        mesh = drop_small_components(mesh, min_component_faces, min_component_fraction)
        if len(mesh.faces) == 0:
            raise NothingSeenError(
                f"no face is seen by {min_seen_fraction:.0%} of the {len(cameras)} cameras in {views}")
        unseen = faces_before - len(mesh.faces)
        mesh = keep_in_sphere(mesh, SPHERE_RIM)  # culling can part a piece at the rim from the object
        at_rim = faces_before - unseen - len(mesh.faces)
        # what culling opened, as extraction does: small holes, slits (and tears the field covers, where
        # fill_covered allows)
        mesh = fill_small_holes(mesh, info.get("fill_holes") or 0.0, field_perimeter=info.get("fill_covered") or 0.0,
                                field_level=info["threshold"],
                                field=lambda p: evaluate_field(model.udf, p, device=device),
                                slit_perimeter=info.get("fill_slits") or 0.0, slit_width=info.get("slit_width") or 0.0)
        mesh.metadata["meshing"] = {**info, "views": str(views), "cameras": len(cameras),
                                    "min_seen_fraction": min_seen_fraction, "faces_unseen": unseen - lids,
                                    "lid_spread": lid_spread, "faces_lids": lids,
                                    "faces_outside": info.get("faces_outside", 0) + at_rim}
    color_vertices(mesh, model.color, device=device, progress=sub_progress(report, 0.9, 0.98))
    mesh = decimate(mesh, faces)
    if texture_size > 0:
        mesh, _ = bake_texture(mesh, views, texture_size, progress=sub_progress(progress, 0.6, 0.99))
    export_mesh(mesh, out_path)
    progress(1.0, f"wrote {out_path}")
    return mesh
