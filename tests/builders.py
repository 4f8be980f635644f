"""Scenes and videos the tests make themselves (bench/capture.py renders its videos with them too).

A walk-around of a textured wavy sheet inside a textured backdrop sphere (the backdrop gives SIFT texture
with parallax, as a room does), encoded as H.264 with PyAV; and frames of noise, sharp and unrelated.
"""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import av
import numpy as np
import trimesh
from PIL import Image

from neudf_core import synthetic
from neudf_core.synthetic import blob_texture

ORBIT_RADIUS = 3.0


def backdrop_sphere(radius: float = 5.0, rings: int = 64, seed: int = 1, texture_size: tuple[int, int] = (1024, 512),
                    n_blobs: int = 3000, blob_px: tuple[float, float] = (3, 16)) -> trimesh.Trimesh:
    """An inside-out textured sphere around the scene: a room's walls, with parallax for SIFT."""
    theta, phi = np.meshgrid(np.linspace(0, 2 * np.pi, 2 * rings + 1), np.linspace(0.05, np.pi - 0.05, rings))
    x, y, z = radius * np.sin(phi) * np.cos(theta), radius * np.cos(phi), radius * np.sin(phi) * np.sin(theta)
    mesh = synthetic._grid_mesh(x, y, z)
    uv = np.stack([theta.ravel() / (2 * np.pi), 1 - phi.ravel() / np.pi], -1)
    mesh.visual = trimesh.visual.TextureVisuals(uv=uv, image=blob_texture(*texture_size, n_blobs, blob_px, seed))
    return mesh


def textured_sheet(seed: int = 0) -> trimesh.Trimesh:
    """The wavy sheet of the synthetic module, in its unit sphere, with a planar UV blob texture."""
    sheet = synthetic.procedural_mesh("wavy_sheet", subdivisions=64)
    sheet.apply_transform(np.linalg.inv(synthetic.unit_sphere_transform(sheet)))
    xz = sheet.vertices[:, [0, 2]]
    uv = (xz - xz.min(axis=0)) / np.ptp(xz, axis=0).max()
    sheet.visual = trimesh.visual.TextureVisuals(uv=uv, image=blob_texture(512, 512, 400, (12, 60), seed))
    return sheet


def render_scene(obj: trimesh.Trimesh, backdrop: trimesh.Trimesh, cameras: list[synthetic.Camera],
                 supersample: int = 2) -> np.ndarray:
    """Render ``obj`` in front of ``backdrop`` (which encloses cameras and object), anti-aliased."""
    hi = [synthetic.Camera(np.diag([supersample, supersample, 1.0]) @ c.K, c.c2w, c.width * supersample,
                           c.height * supersample) for c in cameras]
    fg, mask = synthetic.render(obj, hi, "black")
    bg, _ = synthetic.render(backdrop, hi, "black")
    image = np.where(mask[..., None], fg, bg).astype(np.float32)
    n, h, w = len(cameras), cameras[0].height, cameras[0].width
    image = image.reshape(n, h, supersample, w, supersample, 3).mean(axis=(2, 4))
    return image.round().astype(np.uint8)


def encode_video(path: Path, images: np.ndarray, fps: int = 24, *, codec: str = "libx264",
                 pix_fmt: str = "yuv420p", rotation: int = 0, crf: int = 18, faststart: bool = False,
                 color: dict[str, int] | None = None, input_format: str = "rgb24") -> Path:
    """Encode frames (N, H, W, 3) with PyAV; ``rotation`` (counter-clockwise) goes into the display matrix."""
    options = {"movflags": "faststart"} if faststart else {}
    with av.open(str(path), mode="w", options=options) as container:
        stream = container.add_stream(codec, rate=Fraction(fps))
        stream.width, stream.height, stream.pix_fmt = images.shape[2], images.shape[1], pix_fmt
        # one encoder thread: threaded x264 gives other pixels on each run, and so other poses
        options = {"crf": str(crf), "threads": "1"}
        stream.options = {**options, "preset": "veryfast"} if codec == "libx264" else options
        for key, value in (color or {}).items():
            setattr(stream.codec_context, key, value)
        if rotation:
            stream.set_display_rotation(rotation)
        for image in images:
            frame = av.VideoFrame.from_ndarray(image, format=input_format)
            if color:
                frame = frame.reformat(format=pix_fmt, dst_colorspace=color.get("colorspace"))
                for key, value in color.items():
                    setattr(frame, key, value)
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path


def noise_frames(n: int, width: int = 64, height: int = 48, seed: int = 0) -> np.ndarray:
    """Independent random frames: sharp, decodable, and with nothing in common between them."""
    return np.random.default_rng(seed).integers(0, 256, size=(n, height, width, 3), dtype=np.uint8)


# -- textured scenes for the download (texture bake, export) ------------------------------------------------
SHEET_HALF = 0.6
SHEET_GAP = 0.006  # between the front and the back sheet of a rendered two-sided sheet


def two_sided_texture(cells: int = 32, px_per_cell: int = 8, seed: int = 0) -> Image.Image:
    """Left half: a check of random warm colours, ``cells`` x ``cells``; right half: blue-green stripes
    ``cells`` across. Each side's pattern is finer than a coarse mesh's vertices can hold."""
    rng = np.random.default_rng(seed)
    side = cells * px_per_cell
    warm = rng.uniform([0.55, 0.1, 0.0], [1.0, 0.6, 0.3], size=(cells, cells, 3))
    front = np.repeat(np.repeat(warm, px_per_cell, 0), px_per_cell, 1)
    cool = rng.uniform([0.0, 0.3, 0.5], [0.3, 0.8, 1.0], size=(cells, 3))
    back = np.broadcast_to(np.repeat(cool, px_per_cell, 0)[None], (side, side, 3))
    return Image.fromarray((np.concatenate([front, back], axis=1) * 255).round().astype(np.uint8))


def sheet_grid(n: int, y: float = 0.0) -> trimesh.Trimesh:
    """A flat square sheet in the xz plane, 2 * SHEET_HALF across, n x n quads, its front facing +y."""
    u = np.linspace(-SHEET_HALF, SHEET_HALF, n + 1)
    x, z = np.meshgrid(u, u)
    sheet = synthetic._grid_mesh(x, np.full_like(x, y), z)
    if sheet.face_normals[0, 1] < 0:
        sheet.faces = sheet.faces[:, ::-1]
    return sheet


def two_sided_sheet_scene(texture: Image.Image, n: int = 8) -> trimesh.Trimesh:
    """What a camera sees of a sheet whose sides differ: a front sheet (texture's left half) just above a back
    sheet (right half); the ray caster meets the front from above and the back from below."""
    top, bottom = sheet_grid(n, SHEET_GAP / 2), sheet_grid(n, -SHEET_GAP / 2)
    uv = (top.vertices[:, [0, 2]] + SHEET_HALF) / (2 * SHEET_HALF)
    uv_top = np.stack([uv[:, 0] * 0.5, uv[:, 1]], 1)
    uv_bottom = np.stack([0.5 + uv[:, 0] * 0.5, uv[:, 1]], 1)
    bottom.faces = bottom.faces[:, ::-1]
    scene = trimesh.Trimesh(np.concatenate([top.vertices, bottom.vertices]),
                            np.concatenate([top.faces, bottom.faces + len(top.vertices)]), process=False)
    scene.visual = trimesh.visual.TextureVisuals(uv=np.concatenate([uv_top, uv_bottom]), image=texture)
    return scene


def textured_sheet_dataset(out: Path, n_views: int = 40, size: int = 128, cells: int = 32,
                           grid: int = 12) -> tuple[Path, trimesh.Trimesh]:
    """A NeuS dataset of :func:`two_sided_sheet_scene` from cameras all round it, and the sheet to bake: one
    layer, ``grid`` x ``grid`` quads in the dataset's unit sphere, with vertex colours of the front pattern
    as the sheet's light shows it (the best a vertex can hold of it)."""
    texture = two_sided_texture(cells)
    scene = two_sided_sheet_scene(texture)
    synthetic.write_neus_dataset(out, scene, n_views=n_views, size=size, background="white", with_masks=True)
    to_unit = np.linalg.inv(synthetic.unit_sphere_transform(scene))
    sheet = sheet_grid(grid)
    uv = (sheet.vertices[:, [0, 2]] + SHEET_HALF) / (2 * SHEET_HALF)
    pixels = np.asarray(texture, np.float64) / 255.0
    h, w = pixels.shape[:2]
    col = np.clip((uv[:, 0] * 0.5 * (w - 1)).round().astype(int), 0, w - 1)
    row = np.clip(((1 - uv[:, 1]) * (h - 1)).round().astype(int), 0, h - 1)
    shade = 0.55 + 0.45 * abs(synthetic._LIGHT_DIR[1])
    sheet.visual.vertex_colors = (pixels[row, col] * shade * 255).round().astype(np.uint8)
    sheet.apply_transform(to_unit)
    return out, sheet


def holed_wavy_sheet(n: int) -> trimesh.Trimesh:
    """The synthetic wavy sheet (n x n quads) with a round hole cut out along the grid: two boundary loops,
    their rims jagged as a mesh cut from a distance field has them."""
    sheet = synthetic.procedural_mesh("wavy_sheet", subdivisions=n)
    centres = sheet.triangles_center
    sheet.update_faces(np.hypot(centres[:, 0], centres[:, 2]) > 0.2)
    sheet.remove_unreferenced_vertices()
    return sheet
