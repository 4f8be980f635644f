"""The baked texture: a synthetic sheet whose two sides carry different fine patterns, rendered from cameras
all round it; baked from most of the views, compared at the views held out of the bake."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from neudf_core import synthetic
from neudf_core.dataset import load_cameras
from neudf_core.texture import BACK_OFFSET, bake_texture, rasterize, unwrap
from tests.builders import textured_sheet_dataset

SIZE = 512  # texture px: the sheet's pattern gets ~8 texels per check


@pytest.fixture(scope="module")
def sheet_scene(tmp_path_factory) -> tuple[Path, object]:
    return textured_sheet_dataset(tmp_path_factory.mktemp("sheet") / "data")


def held_out(n: int) -> tuple[list[int], list[int]]:
    held = list(range(0, n, 5))
    return held, [i for i in range(n) if i not in held]


def render_at(mesh, data: Path, frames: list[int]) -> np.ndarray:
    cams = load_cameras(data)
    cameras = [synthetic.Camera(cams.intrinsics[i], cams.c2w[i], cams.width, cams.height) for i in frames]
    return synthetic.render(mesh, cameras, "white", lit=False)[0].astype(np.float64)


def truth(data: Path, frames: list[int]) -> tuple[np.ndarray, np.ndarray]:
    images = np.stack([np.asarray(Image.open(data / "image" / f"{i:03d}.png")) for i in frames]).astype(np.float64)
    masks = np.stack([np.asarray(Image.open(data / "mask" / f"{i:03d}.png")) > 0 for i in frames])
    return images, masks


def psnr(image: np.ndarray, target: np.ndarray, mask: np.ndarray) -> float:
    return float(10 * np.log10(255.0**2 / ((image - target) ** 2)[mask].mean()))


def test_texture_beats_vertex_colours_and_keeps_each_side(sheet_scene):
    data, sheet = sheet_scene
    held, used = held_out(len(load_cameras(data)))
    textured, figures = bake_texture(sheet, data, SIZE, frames=used)
    assert figures["frames"] == len(used) and figures["seen"] > 0.8, figures
    target, masks = truth(data, held)
    baked, plain = render_at(textured, data, held), render_at(sheet, data, held)
    above = np.array([load_cameras(data).c2w[i][1, 3] > 0.3 for i in held])
    below = np.array([load_cameras(data).c2w[i][1, 3] < -0.3 for i in held])
    assert above.any() and below.any()
    for side in (above, below):  # the front's checks and the back's stripes, each from its own side
        mask = masks & side[:, None, None]
        gain = psnr(baked, target, mask) - psnr(plain, target, mask)
        assert gain >= 3.0, gain
        # the side's own colours: mean colour within 4 % of the truth's
        assert np.abs(baked[mask].mean(axis=0) - target[mask].mean(axis=0)).max() < 0.04 * 255
    assert psnr(baked, target, masks) >= psnr(plain, target, masks) + 3.0


def test_frames_of_other_exposure_are_evened_out(sheet_scene, tmp_path):
    """Every other frame 30 % darker (a phone's auto exposure): the per-frame gains take it out."""
    data, sheet = sheet_scene
    dim = tmp_path / "data"
    shutil.copytree(data, dim)
    n = len(load_cameras(data))
    for i in range(1, n, 2):
        path = dim / "image" / f"{i:03d}.png"
        pixels = np.asarray(Image.open(path)).astype(np.float64)
        Image.fromarray((pixels * 0.7).round().astype(np.uint8)).save(path)
    held, used = held_out(n)
    even, _ = bake_texture(sheet, dim, SIZE, frames=used)
    # a gain undoes its frame's exposure, up to one level per side (the two sides share no frame's view)
    gains = np.asarray(even.metadata["texture_gains"]).mean(axis=1)
    evened = gains * np.array([0.7 if i % 2 else 1.0 for i in used])
    height = load_cameras(data).c2w[used, 1, 3]
    for side in (height > 0.3, height < -0.3):
        assert evened[side].std() < 0.03 * evened[side].mean(), gains[side]
    reference, _ = bake_texture(sheet, data, SIZE, frames=used)
    target, masks = truth(data, held)
    baked, clean = render_at(even, data, held), render_at(reference, data, held)
    level = target[masks].mean(axis=0) / baked[masks].mean(axis=0)  # no frame says which exposure is right
    assert psnr(baked * level, target, masks) > psnr(clean, target, masks) - 1.0


def test_atlas_twins_every_face_behind_it(sheet_scene):
    _, sheet = sheet_scene
    atlas = unwrap(sheet, 256)
    n = len(sheet.faces)
    assert len(atlas.faces) == 2 * n and atlas.n_front == n
    front, back = atlas.faces[:n], atlas.faces[n:]
    assert np.array_equal(atlas.source[front], sheet.faces)  # same corners, same order
    assert np.array_equal(atlas.source[back], sheet.faces[:, ::-1])  # reversed winding
    normals = atlas.face_normals()
    assert np.allclose(normals[n:], -normals[:n], atol=1e-6)
    depth = ((atlas.vertices[front].mean(axis=1) - atlas.vertices[back].mean(axis=1)) * normals[:n]).sum(axis=1)
    assert np.allclose(depth, BACK_OFFSET, rtol=0.05)
    assert atlas.uv.min() >= 0.0 and atlas.uv.max() <= 1.0
    # front and back charts lie apart: no texel centre falls in a front face and a back face
    pixels = np.stack([atlas.uv[:, 0] * 256, (1 - atlas.uv[:, 1]) * 256], axis=1)
    front_texels = {int(i) for part in rasterize(pixels, front, 256, 256) for i in part[0]}
    back_texels = {int(i) for part in rasterize(pixels, back, 256, 256) for i in part[0]}
    assert front_texels and back_texels and not front_texels & back_texels
