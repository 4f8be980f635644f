"""Synthetic scenes: render a mesh from known cameras, as images or as a dataset in the NeuS layout.

Tests and benchmarks need images whose cameras and surface are known exactly. We ray-cast the mesh
with trimesh's Embree intersector (a real ray caster, not our own), colour the hits from the mesh's
texture, its vertex colours or a procedural 3-D texture, and shade them with a fixed two-sided light so
both sides of an open surface look alike and no side is black.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import trimesh
from PIL import Image, ImageDraw

Background = Literal["white", "black", "env"]

# A fixed light, so shading is view independent (the colour network still sees the view direction).
_LIGHT_DIR = np.array([0.3, 0.8, 0.5]) / np.linalg.norm([0.3, 0.8, 0.5])


@dataclass
class Camera:
    """A pinhole camera. ``c2w`` follows OpenCV: x right, y down, z forward (into the scene)."""

    K: np.ndarray  # (3, 3) intrinsics in pixels; pixel centres sit at integer + 0.5
    c2w: np.ndarray  # (4, 4) camera to world
    width: int
    height: int

    @property
    def center(self) -> np.ndarray:
        return self.c2w[:3, 3]

    def world_mat(self) -> np.ndarray:
        """The 4x4 projection K [R | t] from world to pixels (NeuS's ``world_mat``)."""
        w2c = np.linalg.inv(self.c2w)
        P = np.eye(4)
        P[:3, :4] = self.K @ w2c[:3, :4]
        return P

    def rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Origins and unit directions of one ray per pixel centre, row-major, each (H*W, 3)."""
        u, v = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=-1)
        dirs = pix @ np.linalg.inv(self.K).T @ self.c2w[:3, :3].T
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
        origins = np.broadcast_to(self.center, dirs.shape).copy()
        return origins, dirs


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 1.0, 0.0])) -> np.ndarray:
    """OpenCV camera-to-world matrix of a camera at ``eye`` looking at ``target`` with ``up`` above."""
    forward = target - eye
    forward = forward / np.linalg.norm(forward)
    down = -(up - np.dot(up, forward) * forward)
    if np.linalg.norm(down) < 1e-8:  # looking straight along up: any perpendicular will do
        down = np.cross(forward, [1.0, 0.0, 0.0])
    down = down / np.linalg.norm(down)
    right = np.cross(down, forward)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, eye
    return c2w


def intrinsics(width: int, height: int, fov_deg: float) -> np.ndarray:
    """Pinhole intrinsics with the given horizontal field of view and a centred principal point."""
    f = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
    return np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])


def orbit_cameras(
    n: int,
    radius: float = 3.0,
    elevation_deg: tuple[float, float] = (-20.0, 40.0),
    width: int = 128,
    height: int = 128,
    fov_deg: float = 40.0,
    turns: float = 1.0,
    target: np.ndarray | None = None,
) -> list[Camera]:
    """A walk-around: ``turns`` circles about the y axis, elevation swinging once between its bounds.

    Consecutive cameras are neighbours, as frames of a video are.
    """
    target = np.zeros(3) if target is None else np.asarray(target, float)
    K = intrinsics(width, height, fov_deg)
    lo, hi = np.radians(elevation_deg)
    cams = []
    for i in range(n):
        phase = i / n
        azimuth = 2 * np.pi * turns * phase
        elevation = lo + (hi - lo) * 0.5 * (1 - np.cos(2 * np.pi * phase))
        eye = target + radius * np.array(
            [np.cos(elevation) * np.sin(azimuth), np.sin(elevation), np.cos(elevation) * np.cos(azimuth)]
        )
        cams.append(Camera(K.copy(), look_at(eye, target), width, height))
    return cams


def sphere_cameras(
    n: int, radius: float = 3.0, width: int = 128, height: int = 128, fov_deg: float = 40.0
) -> list[Camera]:
    """Cameras spread evenly over a whole sphere (a Fibonacci lattice), so both sides of a sheet are seen."""
    K = intrinsics(width, height, fov_deg)
    golden = np.pi * (3 - np.sqrt(5))
    cams = []
    for i in range(n):
        y = 1 - 2 * (i + 0.5) / n
        ring = np.sqrt(1 - y * y)
        eye = radius * np.array([ring * np.cos(golden * i), y, ring * np.sin(golden * i)])
        up = np.array([0.0, 1.0, 0.0]) if abs(y) < 0.99 else np.array([0.0, 0.0, 1.0])
        cams.append(Camera(K.copy(), look_at(eye, np.zeros(3), up), width, height))
    return cams


def procedural_texture(points: np.ndarray, seed: int = 0) -> np.ndarray:
    """A colourful 3-D texture of several frequencies: gives SIFT corners and the photometric loss detail."""
    rng = np.random.default_rng(seed)
    colour = np.zeros((len(points), 3))
    for freq in (4.0, 9.0, 19.0):
        dirs = rng.normal(size=(3, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        phases = rng.uniform(0, 2 * np.pi, size=3)
        colour += np.sin(freq * points @ dirs.T + phases) / freq
    colour = colour / np.abs(colour).max(axis=0, keepdims=True).clip(1e-6)
    # Hard-ish steps between colours read better to a feature detector than smooth waves.
    return np.clip(0.5 + 0.45 * np.tanh(3 * colour), 0, 1)


def _environment(dirs: np.ndarray) -> np.ndarray:
    """A background at infinity that is not blank: bands of colour by direction, lighter above."""
    theta = np.arctan2(dirs[:, 0], dirs[:, 2])
    phi = np.arcsin(np.clip(dirs[:, 1], -1, 1))
    checker = (np.floor(theta * 6 / np.pi) + np.floor(phi * 6 / np.pi)) % 2
    base = np.stack([0.55 + 0.25 * np.sin(3 * theta), 0.6 + 0.2 * np.cos(2 * theta + 1.0), 0.7 + 0.2 * phi], -1)
    return np.clip(base * (0.75 + 0.25 * checker[:, None]), 0, 1)


def _has_detail(image) -> bool:
    """Whether a texture image carries a pattern. An OBJ with UVs but no texture file loads with a
    placeholder image of one colour; rendered as is, the garment would be a blank the photometric loss
    cannot see, so the procedural texture is used instead."""
    pixels = np.asarray(image.convert("RGB"))
    return min(pixels.shape[:2]) >= 8 and bool((pixels.reshape(-1, 3) != pixels.reshape(-1, 3)[0]).any())


def _surface_colour(mesh: trimesh.Trimesh, faces: np.ndarray, points: np.ndarray, seed: int) -> np.ndarray:
    """Albedo at ray hits: from the UV texture, the vertex colours, or a procedural texture."""
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[faces], points)
    visual = mesh.visual
    if visual.kind == "texture" and getattr(visual, "uv", None) is not None and visual.material is not None:
        image = getattr(visual.material, "image", None) or getattr(visual.material, "baseColorTexture", None)
        if image is not None and _has_detail(image):
            tex = np.asarray(image.convert("RGB"), dtype=np.float64) / 255.0
            uv = np.einsum("nk,nkj->nj", bary, visual.uv[mesh.faces[faces]]) % 1.0
            col = np.clip(((uv[:, 0]) * (tex.shape[1] - 1)).round().astype(int), 0, tex.shape[1] - 1)
            row = np.clip(((1 - uv[:, 1]) * (tex.shape[0] - 1)).round().astype(int), 0, tex.shape[0] - 1)
            return tex[row, col]
    if visual.kind == "vertex":
        vc = np.asarray(visual.vertex_colors, dtype=np.float64)[:, :3] / 255.0
        return np.einsum("nk,nkj->nj", bary, vc[mesh.faces[faces]])
    return procedural_texture(points, seed)


def render(
    scene: trimesh.Trimesh,
    cameras: list[Camera],
    background: Background = "white",
    seed: int = 0,
    lit: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast ``scene`` from each camera. Returns images uint8 (N, H, W, 3) and masks bool (N, H, W).

    ``lit=False`` shows the surface colours as they are (a baked texture already holds the light it was
    photographed under)."""
    intersector = trimesh.ray.ray_pyembree.RayMeshIntersector(scene)
    images, masks = [], []
    for cam in cameras:
        origins, dirs = cam.rays()
        tri, ray, loc = intersector.intersects_id(origins, dirs, multiple_hits=False, return_locations=True)
        if background == "env":
            rgb = _environment(dirs)
        else:
            rgb = np.full((len(dirs), 3), 1.0 if background == "white" else 0.0)
        if len(ray):
            albedo = _surface_colour(scene, tri, loc, seed)
            shade = 0.55 + 0.45 * np.abs(scene.face_normals[tri] @ _LIGHT_DIR) if lit else np.ones(len(tri))
            rgb[ray] = albedo * shade[:, None]
        mask = np.zeros(len(dirs), bool)
        mask[ray] = True
        images.append((rgb.reshape(cam.height, cam.width, 3) * 255).round().astype(np.uint8))
        masks.append(mask.reshape(cam.height, cam.width))
    return np.stack(images), np.stack(masks)


def procedural_mesh(
    kind: Literal["sheet", "sheet_with_hole", "bowl", "two_sheets", "wavy_sheet"] = "wavy_sheet",
    size: float = 1.2,
    subdivisions: int = 48,
) -> trimesh.Trimesh:
    """Small open surfaces for tests. Centred at the origin, ``size`` across, no texture (procedural one applies)."""
    n = subdivisions
    u, v = np.meshgrid(np.linspace(-0.5, 0.5, n + 1), np.linspace(-0.5, 0.5, n + 1))
    if kind == "bowl":
        return _bowl(size / 2, n)
    x, z = u * size, v * size
    y = 0.12 * size * np.sin(2.5 * x / size * np.pi) * np.cos(1.5 * z / size * np.pi) if kind == "wavy_sheet" else 0 * x
    sheet = _grid_mesh(x, y, z)
    if kind == "sheet_with_hole":
        centres = sheet.triangles_center
        keep = np.hypot(centres[:, 0], centres[:, 2]) > 0.18 * size
        sheet.update_faces(keep)
        sheet.remove_unreferenced_vertices()
    if kind == "two_sheets":
        top = sheet.copy()
        top.apply_translation([0, 0.2 * size, 0])
        sheet.apply_translation([0, -0.2 * size, 0])
        return trimesh.util.concatenate([top, sheet])
    return sheet


def _grid_mesh(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> trimesh.Trimesh:
    rows, cols = x.shape
    vertices = np.stack([x.ravel(), np.broadcast_to(y, x.shape).ravel(), z.ravel()], -1)
    idx = np.arange(rows * cols).reshape(rows, cols)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    return trimesh.Trimesh(vertices, faces, process=False)


def _bowl(radius: float, n: int) -> trimesh.Trimesh:
    """A hemisphere open at the top: one boundary loop."""
    theta, phi = np.meshgrid(np.linspace(0, 2 * np.pi, 2 * n + 1), np.linspace(0.02, np.pi / 2, n))
    x = radius * np.sin(phi) * np.cos(theta)
    z = radius * np.sin(phi) * np.sin(theta)
    y = -radius * np.cos(phi) + radius / 2
    mesh = _grid_mesh(x, y, z)
    mesh.merge_vertices()  # close the seam at theta = 0 = 2 pi
    # phi starts just off the pole to avoid degenerate triangles; a small fan closes the pole.
    ring = np.where(np.isclose(mesh.vertices[:, 1], y[0, 0]))[0]
    centre = len(mesh.vertices)
    angles = np.arctan2(mesh.vertices[ring, 2], mesh.vertices[ring, 0])
    ring = ring[np.argsort(angles)]
    cap = [[centre, ring[(i + 1) % len(ring)], ring[i]] for i in range(len(ring))]
    vertices = np.vstack([mesh.vertices, [[0.0, -radius + radius / 2, 0.0]]])
    return trimesh.Trimesh(vertices, np.vstack([mesh.faces, cap]), process=True)


def blob_texture(width: int, height: int, n_blobs: int, size_px: tuple[float, float], seed: int) -> Image.Image:
    """Random coloured ellipses and rectangles over a soft noise: corners and blobs at many scales for SIFT."""
    rng = np.random.default_rng(seed)
    base = rng.integers(60, 200, size=(height // 16 + 1, width // 16 + 1, 3)).astype(np.uint8)
    image = Image.fromarray(base).resize((width, height), Image.BICUBIC)
    draw = ImageDraw.Draw(image)
    for _ in range(n_blobs):
        size = np.exp(rng.uniform(np.log(size_px[0]), np.log(size_px[1])))
        x, y = rng.uniform(0, width), rng.uniform(0, height)
        box = [x, y, x + size * rng.uniform(0.6, 1.6), y + size * rng.uniform(0.6, 1.6)]
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        (draw.ellipse if rng.random() < 0.5 else draw.rectangle)(box, fill=colour)
    return image


def _textured_quad(corner: np.ndarray, edge_u: np.ndarray, edge_v: np.ndarray, tile: float,
                   image: Image.Image) -> trimesh.Trimesh:
    """A rectangle (two triangles) whose texture repeats every ``tile`` units along both edges."""
    vertices = np.stack([corner, corner + edge_u, corner + edge_u + edge_v, corner + edge_v])
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float) * [np.linalg.norm(edge_u) / tile,
                                                             np.linalg.norm(edge_v) / tile]
    quad = trimesh.Trimesh(vertices, [[0, 1, 2], [0, 2, 3]], process=False)
    quad.visual = trimesh.visual.TextureVisuals(uv=uv, image=image)
    return quad


@dataclass
class Room:
    """A garment in a furnished room: what a phone video of it sees. ``parts[0]`` is the object."""

    parts: list[trimesh.Trimesh]
    floor_y: float


def room_scene(obj: trimesh.Trimesh, floor_y: float = -1.25, half_size: float = 5.0, height: float = 4.5,
               seed: int = 0) -> Room:
    """``obj`` (in its unit sphere) hanging above a textured floor, in a room with textured walls and a few
    boxes standing about outside the camera path: floors, walls, clutter and the object's shadow are in view."""
    rng = np.random.default_rng(seed)
    floor_img = blob_texture(1024, 1024, 1500, (6, 40), seed + 11)
    wall_img = blob_texture(1024, 1024, 1200, (8, 60), seed + 12)
    s, y0, y1 = half_size, floor_y, floor_y + height
    parts = [obj, _textured_quad(np.array([-s, y0, -s]), np.array([0, 0, 2 * s]), np.array([2 * s, 0, 0]), 2.0,
                                 floor_img)]
    for corner, edge in (([-s, y0, -s], [2 * s, 0, 0]), ([s, y0, -s], [0, 0, 2 * s]), ([s, y0, s], [-2 * s, 0, 0]),
                         ([-s, y0, s], [0, 0, -2 * s])):
        parts.append(_textured_quad(np.array(corner, float), np.array(edge, float), np.array([0, height, 0]), 2.5,
                                    wall_img))
    parts.append(_textured_quad(np.array([-s, y1, -s]), np.array([2 * s, 0, 0]), np.array([0, 0, 2 * s]), 3.0,
                                wall_img))
    for i, angle in enumerate(rng.uniform(0, 2 * np.pi, 4)):
        size = rng.uniform(0.4, 0.9, 3)
        box = trimesh.creation.box(size)
        box.apply_translation([4.0 * np.sin(angle), floor_y + size[1] / 2, 4.0 * np.cos(angle)])
        box.visual = trimesh.visual.TextureVisuals(
            uv=(box.vertices[:, [0, 2]] + box.vertices[:, [1, 1]]) % 1.0,
            image=blob_texture(256, 256, 120, (6, 30), seed + 20 + i))
        parts.append(box)
    return Room(parts, floor_y)


def handheld_orbit(n: int, radius: float = 2.5, width: int = 720, height: int = 1280, fov_deg: float = 42.0,
                   elevation_deg: tuple[float, float] = (8.0, 30.0), seed: int = 0) -> list[Camera]:
    """One walk around the origin as a hand holds a phone: the distance, height, aim and roll wander smoothly."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / n

    def wander(amplitude: float) -> np.ndarray:  # a few slow sines with random phases, about +-amplitude
        waves = [np.sin(2 * np.pi * (k * t + rng.uniform())) / k for k in (1, 2, 3, 5)]
        return amplitude * np.sum(waves, axis=0) / 1.6

    lo, hi = np.radians(elevation_deg)
    elevation = lo + (hi - lo) * 0.5 * (1 - np.cos(2 * np.pi * t)) + np.radians(wander(2.0))
    azimuth = 2 * np.pi * t + np.radians(wander(3.0))
    dist = radius + wander(0.08)
    K = intrinsics(width, height, fov_deg)
    cams = []
    for i in range(n):
        eye = dist[i] * np.array([np.cos(elevation[i]) * np.sin(azimuth[i]), np.sin(elevation[i]),
                                  np.cos(elevation[i]) * np.cos(azimuth[i])])
        aim = np.array([wander(0.05)[i], wander(0.05)[i], wander(0.05)[i]])
        roll = np.radians(wander(2.0)[i])
        c2w = look_at(eye, aim)
        spin = np.array([[np.cos(roll), -np.sin(roll), 0], [np.sin(roll), np.cos(roll), 0], [0, 0, 1]])
        c2w[:3, :3] = c2w[:3, :3] @ spin
        cams.append(Camera(K.copy(), c2w, width, height))
    return cams


def render_room(room: Room, cameras: list[Camera], seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast a room: images uint8 (N, H, W, 3) and object masks (N, H, W); the object casts a shadow on
    everything under the light, as a lamp above it would."""
    scene = trimesh.util.concatenate([trimesh.Trimesh(p.vertices, p.faces, process=False) for p in room.parts])
    offsets = np.cumsum([0] + [len(p.faces) for p in room.parts])
    hit_scene = trimesh.ray.ray_pyembree.RayMeshIntersector(scene)
    occluder = trimesh.ray.ray_pyembree.RayMeshIntersector(room.parts[0])
    images, masks = [], []
    for cam in cameras:
        origins, dirs = cam.rays()
        tri, ray, loc = hit_scene.intersects_id(origins, dirs, multiple_hits=False, return_locations=True)
        rgb = np.zeros((len(dirs), 3))
        part = np.searchsorted(offsets, tri, side="right") - 1
        shade = 0.55 + 0.45 * np.abs(scene.face_normals[tri] @ _LIGHT_DIR)
        lit = np.ones(len(ray))
        behind = part > 0
        if behind.any():  # shadow rays from what the object may shade, towards the light
            start = loc[behind] + 1e-4 * _LIGHT_DIR
            blocked = occluder.intersects_any(start, np.broadcast_to(_LIGHT_DIR, start.shape))
            lit[np.flatnonzero(behind)[blocked]] = 0.45
        for k, mesh in enumerate(room.parts):
            sel = part == k
            if sel.any():
                rgb[ray[sel]] = _surface_colour(mesh, tri[sel] - offsets[k], loc[sel], seed)
        rgb[ray] *= (shade * lit)[:, None]
        mask = np.zeros(len(dirs), bool)
        mask[ray[part == 0]] = True
        images.append((rgb.reshape(cam.height, cam.width, 3) * 255).round().astype(np.uint8))
        masks.append(mask.reshape(cam.height, cam.width))
    return np.stack(images), np.stack(masks)


def unit_sphere_transform(mesh: trimesh.Trimesh, fill: float = 0.8) -> np.ndarray:
    """The 4x4 ``scale_mat``: maps the unit sphere into world so the mesh fills ``fill`` of its radius."""
    centre = mesh.bounds.mean(axis=0)
    radius = np.linalg.norm(mesh.vertices - centre, axis=1).max() / fill
    scale_mat = np.eye(4)
    scale_mat[:3, :3] *= radius
    scale_mat[:3, 3] = centre
    return scale_mat


def write_neus_dataset(
    out_dir: str | Path,
    mesh: trimesh.Trimesh,
    n_views: int = 32,
    size: int = 96,
    background: Background = "white",
    radius: float = 3.0,
    fov_deg: float = 40.0,
    with_masks: bool = True,
    seed: int = 0,
) -> Path:
    """Render ``mesh`` (in any world frame) from cameras spread over a sphere and write the NeuS layout.

    Writes image/*.png, mask/*.png, cameras_sphere.npz (world_mat_i world->pixels and scale_mat_i unit
    sphere->world, as real captures have them), mesh_gt.ply in unit-sphere coordinates, and scene.json.
    """
    out = Path(out_dir)
    (out / "image").mkdir(parents=True, exist_ok=True)
    scale_mat = unit_sphere_transform(mesh)
    unit_mesh = mesh.copy()
    unit_mesh.apply_transform(np.linalg.inv(scale_mat))
    cameras = sphere_cameras(n_views, radius, size, size, fov_deg)
    images, masks = render(unit_mesh, cameras, background, seed)
    arrays = {}
    for i, (cam, image, mask) in enumerate(zip(cameras, images, masks)):
        Image.fromarray(image).save(out / "image" / f"{i:03d}.png")
        if with_masks:
            (out / "mask").mkdir(exist_ok=True)
            Image.fromarray((mask * 255).astype(np.uint8)).save(out / "mask" / f"{i:03d}.png")
        # The camera lives in unit-sphere coordinates; NeuS stores it in world, undone by scale_mat.
        arrays[f"world_mat_{i}"] = cam.world_mat() @ np.linalg.inv(scale_mat)
        arrays[f"scale_mat_{i}"] = scale_mat
    np.savez(out / "cameras_sphere.npz", **arrays)
    unit_mesh.export(out / "mesh_gt.ply")
    info = {"views": n_views, "size": size, "background": background, "radius": radius, "fov_deg": fov_deg}
    (out / "scene.json").write_text(json.dumps(info, indent=2))
    return out
