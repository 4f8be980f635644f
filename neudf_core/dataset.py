"""The NeuS / NeUDF dataset layout: image/*.png, optional mask/*.png, cameras_sphere.npz.

``cameras_sphere.npz`` holds, per image i, ``world_mat_i`` (K [R | t], world to pixels) and
``scale_mat_i`` (unit sphere to world). The camera in unit-sphere coordinates is
P_i = world_mat_i @ scale_mat_i; ``scale_mat_i`` may differ per view and may hold a rotation, so it is
never assumed diagonal.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from PIL import Image
from torch import Tensor


class DatasetError(ValueError):
    """A dataset folder that cannot be used, with the reason in words."""


REGION_FILE = "region.json"  # optional: {"floor_y": height in the unit sphere (y up) below which lies no object}
OBJECT_POINTS_FILE = "object_points.npy"  # optional: (M, 3) sparse points of the object, in the unit sphere
# optional, with it: (M, VIEWS_PER_POINT) int indices of images that saw each point (the capture's tracks), -1 after
OBJECT_POINT_VIEWS_FILE = "object_point_views.npy"
VIEWS_PER_POINT = 8
# Height over the floor cut (unit sphere) that still holds the floor's own points and the object's shadow:
# beer.mp4's shadow spread 0.05 over its floor, and the floor's points scatter that far above its level.
FLOOR_SHADOW_BAND = 0.1


@dataclass
class Dataset:
    images: Tensor  # (N, H, W, 3) float 0..1
    masks: Tensor | None  # (N, H, W) float 0..1
    intrinsics: Tensor  # (N, 3, 3) in pixels of ``images``
    c2w: Tensor  # (N, 4, 4), OpenCV camera to unit-sphere world
    names: list[str]
    object_pixels: Tensor | None = None  # flat (image, y, x) indices of the pixels whose rays meet the unit sphere
    near_points: Tensor | None = None  # (N, H, W) bool: the pixel's ray passes near a sparse point of the object

    @property
    def n_images(self) -> int:
        return self.images.shape[0]

    @property
    def height(self) -> int:
        return self.images.shape[1]

    @property
    def width(self) -> int:
        return self.images.shape[2]

    def to(self, device: str | torch.device) -> "Dataset":
        masks = self.masks.to(device) if self.masks is not None else None
        pixels = self.object_pixels.to(device) if self.object_pixels is not None else None
        near = self.near_points.to(device) if self.near_points is not None else None
        return Dataset(self.images.to(device), masks, self.intrinsics.to(device), self.c2w.to(device), self.names,
                       pixels, near)

    def rays(self, image_idx: Tensor, pixel_y: Tensor, pixel_x: Tensor) -> tuple[Tensor, Tensor]:
        """World-space origins and unit directions through pixel centres."""
        pix = torch.stack([pixel_x + 0.5, pixel_y + 0.5, torch.ones_like(pixel_x)], -1).float()
        dirs_cam = torch.linalg.solve(self.intrinsics[image_idx], pix[..., None])[..., 0]
        c2w = self.c2w[image_idx]
        dirs = (c2w[:, :3, :3] @ dirs_cam[..., None])[..., 0]
        return c2w[:, :3, 3], dirs / dirs.norm(dim=-1, keepdim=True)

    def find_object_pixels(self) -> None:
        """Mark the pixels whose rays meet the unit sphere: only those can see the object."""
        found = []
        ys, xs = torch.meshgrid(torch.arange(self.height), torch.arange(self.width), indexing="ij")
        ys, xs = ys.reshape(-1).to(self.images.device), xs.reshape(-1).to(self.images.device)
        for i in range(self.n_images):
            origin, dirs = self.rays(torch.full_like(ys, i), ys, xs)
            # |o + t d| = 1 has a solution when the ray's closest approach to the centre is inside the sphere
            along = (origin * dirs).sum(-1)
            closest = (origin * origin).sum(-1) - along**2
            hit = torch.nonzero(closest < 1.0)[:, 0]
            found.append(i * self.height * self.width + hit)
        self.object_pixels = torch.cat(found)

    def find_near_points(self, points: Tensor, radius: float) -> None:
        """Mark, per image, the pixels within ``radius`` (unit sphere, at the point's depth) of a projected
        sparse point of the object: where the object may be. The rest of the sphere's pixels see past it."""
        near = torch.zeros(self.n_images, self.height, self.width, dtype=torch.bool)
        points = points.to(self.c2w.device).float()
        for i in range(self.n_images):
            rotation, origin = self.c2w[i, :3, :3], self.c2w[i, :3, 3]
            cam = (points - origin) @ rotation  # world to the camera's axes (OpenCV: z forward)
            cam = cam[cam[:, 2] > 1e-3]
            pix = cam @ self.intrinsics[i].T
            uv = pix[:, :2] / pix[:, 2:3]
            inside = (uv[:, 0] >= 0) & (uv[:, 0] < self.width) & (uv[:, 1] >= 0) & (uv[:, 1] < self.height)
            if not bool(inside.any()):
                continue
            hit = torch.zeros(self.height, self.width, device=uv.device)
            hit[uv[inside, 1].long(), uv[inside, 0].long()] = 1.0
            # one splat size per image: the radius seen at the points' median depth
            r_px = max(1, round(float(radius * self.intrinsics[i, 0, 0] / cam[inside, 2].median())))
            grown = torch.nn.functional.max_pool2d(hit[None, None], 2 * r_px + 1, stride=1, padding=r_px)[0, 0]
            near[i] = grown.cpu() > 0
        self.near_points = near.to(self.images.device)

    def sample_rays(self, n_rays: int, images_per_batch: int, generator: torch.Generator | None = None,
                    object_share: float = 0.0) -> dict:
        """n random rays from ``images_per_batch`` random images (the paper: 512 rays from 8 images).

        ``object_share`` of them come from pixels whose rays meet the unit sphere (all images); the rest of
        a video's frame shows only the surroundings, which the background model alone learns from.
        """
        device = self.images.device
        n_object = int(round(n_rays * object_share)) if self.object_pixels is not None else 0
        n_any = n_rays - n_object
        k = min(images_per_batch, self.n_images) if images_per_batch > 0 else self.n_images
        chosen = torch.randperm(self.n_images, generator=generator)[:k].to(device)
        image_idx = chosen[torch.randint(0, k, (n_any,), generator=generator).to(device)]
        y = torch.randint(0, self.height, (n_any,), generator=generator).to(device)
        x = torch.randint(0, self.width, (n_any,), generator=generator).to(device)
        if n_object:
            pick = torch.randint(0, len(self.object_pixels), (n_object,), generator=generator).to(device)
            flat = self.object_pixels[pick]
            image_idx = torch.cat([image_idx, flat // (self.height * self.width)])
            y = torch.cat([y, flat // self.width % self.height])
            x = torch.cat([x, flat % self.width])
        rays_o, rays_d = self.rays(image_idx, y, x)
        batch = {"rays_o": rays_o, "rays_d": rays_d, "color": self.images[image_idx, y, x]}
        if self.masks is not None:
            batch["mask"] = self.masks[image_idx, y, x]
        if self.near_points is not None:
            batch["near_points"] = self.near_points[image_idx, y, x].float()
        return batch

    def image_rays(self, index: int, size: int) -> tuple[Tensor, Tensor, tuple[int, int]]:
        """Rays of a whole image rendered at ``size`` pixels on its longest side (for validation)."""
        scale = size / max(self.height, self.width)
        h, w = max(1, round(self.height * scale)), max(1, round(self.width * scale))
        ys = (torch.arange(h, device=self.images.device) + 0.5) / scale - 0.5
        xs = (torch.arange(w, device=self.images.device) + 0.5) / scale - 0.5
        gy, gx = torch.meshgrid(ys, xs, indexing="ij")
        idx = torch.full((h * w,), index, device=self.images.device)
        rays_o, rays_d = self.rays(idx, gy.reshape(-1), gx.reshape(-1))
        return rays_o, rays_d, (h, w)


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split a 3x4 projection into intrinsics K (3x3) and an OpenCV camera-to-world matrix (4x4)."""
    K, R, t = cv2.decomposeProjectionMatrix(P[:3, :4])[:3]
    K = K / K[2, 2]
    c2w = np.eye(4)
    c2w[:3, :3] = R.T
    c2w[:3, 3] = (t[:3] / t[3])[:, 0]
    return K, c2w


def _read_image(path: Path, size: tuple[int, int] | None, grey: bool) -> np.ndarray:
    try:
        img = Image.open(path)
        img = img.convert("L" if grey else "RGB")
    except Exception as exc:  # PIL raises many types for a broken file
        raise DatasetError(f"cannot read image {path}: {exc}") from exc
    if size is not None and img.size != size:
        img = img.resize(size, Image.Resampling.BILINEAR if grey else Image.Resampling.LANCZOS)
    return np.asarray(img, dtype=np.float32) / 255.0


@dataclass
class Cameras:
    """The cameras of a dataset without its images: enough to ask what each view sees."""

    intrinsics: np.ndarray  # (N, 3, 3) in pixels of the full-size images
    c2w: np.ndarray  # (N, 4, 4), OpenCV camera to unit-sphere world
    width: int
    height: int

    def __len__(self) -> int:
        return len(self.c2w)


def image_paths(root: Path) -> list[Path]:
    """The frames of a NeuS-layout folder (image/*.png or *.jpg), in camera order."""
    if not root.is_dir():
        raise DatasetError(f"dataset folder {root} does not exist")
    paths = sorted((root / "image").glob("*.png")) + sorted((root / "image").glob("*.jpg"))
    if not paths:
        raise DatasetError(f"no images in {root / 'image'} (expected image/*.png)")
    return paths


def _projections(root: Path, n: int) -> list[np.ndarray]:
    """P_i = world_mat_i @ scale_mat_i for images 0..n-1: unit sphere to pixels."""
    cam_file = root / "cameras_sphere.npz"
    if not cam_file.is_file():
        raise DatasetError(f"{cam_file} is missing (NeuS layout: world_mat_i and scale_mat_i per image)")
    cams = np.load(cam_file)
    missing = [i for i in range(n) if f"world_mat_{i}" not in cams or f"scale_mat_{i}" not in cams]
    if missing:
        raise DatasetError(
            f"{cam_file.name} has no world_mat/scale_mat for image index {missing[0]} "
            f"({len(missing)} of {n} images lack cameras)"
        )
    return [cams[f"world_mat_{i}"] @ cams[f"scale_mat_{i}"] for i in range(n)]


def load_cameras(root: str | Path) -> Cameras:
    """The cameras of a NeuS-layout folder in unit-sphere coordinates; reads one image only, for its size."""
    root = Path(root)
    paths = image_paths(root)
    with Image.open(paths[0]) as first:
        width, height = first.size
    Ks, c2ws = zip(*(decompose_projection(P) for P in _projections(root, len(paths))))
    return Cameras(np.stack(Ks), np.stack(c2ws), width, height)


def sphere_diameter_px(projections: list[np.ndarray]) -> float:
    """Median over the views of the unit sphere's diameter in pixels (the object's extent, for sizing images)."""
    Ks, c2ws = zip(*(decompose_projection(P) for P in projections))
    return cameras_sphere_px(np.stack(Ks), np.stack(c2ws))


def cameras_sphere_px(intrinsics: np.ndarray, c2w: np.ndarray) -> float:
    """:func:`sphere_diameter_px` of cameras given as (N, 3, 3) intrinsics and (N, 4, 4) camera-to-world."""
    distance = np.maximum(np.linalg.norm(c2w[:, :3, 3], axis=1), 1.0 + 1e-6)
    return float(np.median(2.0 * intrinsics[:, 0, 0] / np.sqrt(distance**2 - 1.0)))


def training_scale(width: int, height: int, projections: list[np.ndarray], max_size: int, sphere_px: int) -> float:
    """The factor training images are scaled by: no upscaling, the longest side at most ``max_size`` and the
    unit sphere about ``sphere_px`` across (each 0 = no limit)."""
    scale = 1.0
    if max_size > 0:
        scale = min(scale, max_size / max(width, height))
    if sphere_px > 0:
        scale = min(scale, sphere_px / sphere_diameter_px(projections))
    return scale


def read_floor(root: str | Path) -> float | None:
    path = Path(root) / REGION_FILE
    if not path.is_file():
        return None
    try:
        value = json.loads(path.read_text()).get("floor_y")
    except (OSError, ValueError) as exc:
        raise DatasetError(f"cannot read {path}: {exc}") from exc
    return None if value is None else float(value)


def _optional_array(path: Path) -> np.ndarray | None:
    """An optional .npy file of a dataset folder: None when absent, a DatasetError when unreadable."""
    if not path.is_file():
        return None
    try:
        return np.load(path)
    except (OSError, ValueError) as exc:
        raise DatasetError(f"cannot read {path}: {exc}") from exc


def read_object_points(root: str | Path) -> np.ndarray | None:
    path = Path(root) / OBJECT_POINTS_FILE
    points = _optional_array(path)
    if points is not None and (points.ndim != 2 or points.shape[1] != 3):
        raise DatasetError(f"{path} holds an array of shape {points.shape}, not (M, 3) points")
    return points


def read_object_point_views(root: str | Path, n_points: int, n_images: int) -> np.ndarray | None:
    """The images that saw each sparse point (row for row with :func:`read_object_points`), or None when the
    capture did not record them."""
    path = Path(root) / OBJECT_POINT_VIEWS_FILE
    views = _optional_array(path)
    if views is None:
        return None
    if views.ndim != 2 or len(views) != n_points or not np.issubdtype(views.dtype, np.integer):
        raise DatasetError(f"{path} holds an array of shape {views.shape} ({views.dtype}), not integer views for "
                           f"each of the {n_points} points in {OBJECT_POINTS_FILE}")
    if views.size and (views.max() >= n_images or views.min() < -1):
        raise DatasetError(f"{path} names images outside 0..{n_images - 1}")
    return views


def load_dataset(root: str | Path, max_size: int = 0, use_masks: bool = False, sphere_px: int = 0) -> Dataset:
    """Read a NeuS-layout folder; ``max_size`` > 0 and ``sphere_px`` > 0 downsize images (and intrinsics) for
    training (see :func:`training_scale`)."""
    root = Path(root)
    paths = image_paths(root)
    projections = _projections(root, len(paths))
    mask_paths = None
    if use_masks:
        mask_paths = sorted((root / "mask").glob("*.png"))
        if len(mask_paths) != len(paths):
            raise DatasetError(f"{len(mask_paths)} masks for {len(paths)} images in {root / 'mask'}")

    first = Image.open(paths[0])
    width, height = first.size
    scale = training_scale(width, height, projections, max_size, sphere_px)
    size = (max(1, round(width * scale)), max(1, round(height * scale)))
    images, masks, Ks, c2ws = [], [], [], []
    for i, path in enumerate(paths):
        with Image.open(path) as probe:
            if probe.size != (width, height):
                raise DatasetError(f"{path.name} is {probe.size[0]}x{probe.size[1]}, others are {width}x{height}")
        images.append(_read_image(path, size, grey=False))
        if mask_paths is not None:
            masks.append(_read_image(mask_paths[i], size, grey=True))
        K, c2w = decompose_projection(projections[i])
        K[0, :] *= size[0] / width
        K[1, :] *= size[1] / height
        Ks.append(K)
        c2ws.append(c2w)
    as_t = lambda a: torch.from_numpy(np.stack(a)).float()  # noqa: E731
    return Dataset(
        images=as_t(images),
        masks=as_t(masks) if mask_paths is not None else None,
        intrinsics=as_t(Ks),
        c2w=as_t(c2ws),
        names=[p.name for p in paths],
    )
