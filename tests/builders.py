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
