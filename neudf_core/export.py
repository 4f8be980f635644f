"""Writing meshes for users: GLB for the web, PLY and OBJ for tools, USDZ for phones.

GLB keeps the vertex colours (COLOR_0) or the baked texture (baseColorTexture, JPEG inside the file) and
gets a double-sided material: an open surface shows its back faces (the inside of a sleeve), which viewers
cull by default (glTF 2.0 spec, material.doubleSided). A textured OBJ comes with its MTL and PNG beside it
(``mesh.obj``, ``mesh.mtl``, ``mesh.png``). USDZ (iOS AR Quick Look) holds a UsdGeom mesh with an ``st``
primvar and a UsdPreviewSurface reading the texture, y up, in metres: the unit sphere becomes an object
``2 * metres_per_unit`` across, standing on y = 0.
"""

from __future__ import annotations

import io
import tempfile
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image
from trimesh.exchange.gltf import export_glb

from neudf_core.files import atomic_write

__all__ = ["SUFFIXES", "USDZ_METRES_PER_UNIT", "export_mesh", "texture_image", "write_obj", "write_usdz"]

SUFFIXES = (".glb", ".ply", ".obj", ".usdz")
# The unit sphere is 2 units across; a phone shows the object 0.5 m across, a plausible size for a garment
# on a hanger, a plant, a book (a capture has no scale of its own).
USDZ_METRES_PER_UNIT = 0.25
# A photographic texture: a fraction of the PNG's size, no visible loss; no chroma subsampling, which would
# blur fine colour patterns (a printed label) by a texel or two.
JPEG_QUALITY = 90

# matte and non-metallic, so the vertex colours show as they are (they multiply the base colour)
_MATERIAL = {
    "name": "neudf-open-surface",
    "pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0, "roughnessFactor": 1.0},
    "doubleSided": True,
}


def _double_sided(tree: dict) -> None:
    """glTF tree post-processor: every primitive gets a double-sided material."""
    materials = tree.setdefault("materials", [])
    for material in materials:
        material["doubleSided"] = True
    default = None
    for mesh in tree.get("meshes", []):
        for primitive in mesh.get("primitives", []):
            if "material" not in primitive:
                if default is None:
                    default = len(materials)
                    materials.append(dict(_MATERIAL))
                primitive["material"] = default
    if not materials:
        del tree["materials"]


def texture_image(mesh: trimesh.Trimesh) -> Image.Image | None:
    """The base-colour image of a textured mesh (None for vertex colours or a texture without an image)."""
    if mesh.visual.kind != "texture" or getattr(mesh.visual, "uv", None) is None:
        return None
    material = mesh.visual.material
    image = getattr(material, "baseColorTexture", None) or getattr(material, "image", None)
    return image.convert("RGB") if image is not None else None


def _as_jpeg(image: Image.Image) -> Image.Image:
    """``image`` as a decoded JPEG that trimesh embeds as JPEG (anything else it embeds as PNG). trimesh encodes
    it again; the image's ``encoderinfo`` has Pillow keep its quantisation tables, so that adds next to no loss."""
    buffer = io.BytesIO()
    image.convert("RGB").save(buffer, format="JPEG", quality=JPEG_QUALITY, subsampling=0)
    jpeg = Image.open(io.BytesIO(buffer.getvalue()))
    jpeg.encoderinfo = {"quality": "keep"}
    return jpeg


def _glb_bytes(mesh: trimesh.Trimesh) -> bytes:
    image = texture_image(mesh)
    if image is not None:
        mesh = mesh.copy()
        mesh.visual.material.baseColorTexture = _as_jpeg(image)
    return export_glb(mesh.scene(), include_normals=True, tree_postprocessor=_double_sided)


def export_mesh(mesh: trimesh.Trimesh, path: str | Path) -> Path:
    """Write ``mesh`` to ``path``; the suffix picks the format (.glb, .ply, .obj, .usdz). Returns the path.

    Raises ValueError for another suffix or a mesh without faces. Parent folders are created; each file is
    written whole or not at all.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise ValueError(f"unknown mesh format {path.suffix or '(no suffix)'!r} for {path}: use {', '.join(SUFFIXES)}")
    if len(mesh.faces) == 0:
        raise ValueError("refusing to write a mesh with no faces")
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".obj":
        return write_obj(mesh, path)
    if suffix == ".usdz":
        return write_usdz(mesh, path)
    if suffix == ".glb":
        data = _glb_bytes(mesh)
    else:
        data = trimesh.exchange.ply.export_ply(mesh, encoding="binary", vertex_normal=True)
    with atomic_write(path) as tmp:
        tmp.write_bytes(data)
    return path


_MTL = """# neudf: the baked texture, unlit colour (Kd 1 so viewers show the image as it is)
newmtl {name}
Ka 1.000000 1.000000 1.000000
Kd 1.000000 1.000000 1.000000
Ks 0.000000 0.000000 0.000000
d 1.000000
illum 1
map_Kd {image}
"""


def write_obj(mesh: trimesh.Trimesh, path: str | Path) -> Path:
    """OBJ; a textured mesh also gets ``<stem>.mtl`` and ``<stem>.png`` beside it (the OBJ names them)."""
    path = Path(path)
    image = texture_image(mesh)
    if image is None:
        text = trimesh.exchange.obj.export_obj(mesh, include_normals=True, include_color=True, include_texture=False)
    else:
        text, _ = trimesh.exchange.obj.export_obj(mesh, include_normals=True, include_texture=True,
                                                  return_texture=True, mtl_name=path.with_suffix(".mtl").name)
        png = path.with_suffix(".png")
        with atomic_write(png) as tmp:
            image.save(tmp, format="PNG")
        with atomic_write(path.with_suffix(".mtl")) as tmp:
            tmp.write_text(_MTL.format(name=mesh.visual.material.name, image=png.name))
    with atomic_write(path) as tmp:
        tmp.write_text(text)
    return path


def usdz_points(vertices: np.ndarray, metres_per_unit: float) -> np.ndarray:
    """Unit-sphere points in metres, the object centred over the origin and standing on y = 0."""
    points = np.asarray(vertices, np.float64) * metres_per_unit
    centre = (points.min(axis=0) + points.max(axis=0)) / 2
    return points - [centre[0], points[:, 1].min(), centre[2]]


def write_usdz(mesh: trimesh.Trimesh, path: str | Path, metres_per_unit: float = USDZ_METRES_PER_UNIT) -> Path:
    """USDZ for AR Quick Look: mesh, normals, ``st`` and a UsdPreviewSurface with the texture (vertex colours
    as a ``displayColor`` primvar when there is no texture)."""
    from pxr import Usd, UsdUtils  # usd-core: imported only when a USDZ is written

    path = Path(path)
    with tempfile.TemporaryDirectory(prefix="neudf-usdz-") as folder:
        root = Path(folder)
        stage = Usd.Stage.CreateNew(str(root / "mesh.usdc"))
        _usd_mesh(stage, mesh, metres_per_unit, root)
        stage.GetRootLayer().Save()
        with atomic_write(path) as tmp:
            if not UsdUtils.CreateNewUsdzPackage(str(root / "mesh.usdc"), str(tmp)):
                raise ValueError(f"usd-core could not package {path.name}")
    return path


def _usd_mesh(stage, mesh: trimesh.Trimesh, metres_per_unit: float, folder: Path) -> None:
    from pxr import Gf, Sdf, UsdGeom, UsdShade, Vt

    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, "/Root")
    stage.SetDefaultPrim(root.GetPrim())
    geom = UsdGeom.Mesh.Define(stage, "/Root/Mesh")
    points = usdz_points(mesh.vertices, metres_per_unit)
    geom.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points.astype(np.float32)))
    geom.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(mesh.faces), 3, np.int32)))
    geom.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.asarray(mesh.faces, np.int32).ravel()))
    geom.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(mesh.vertex_normals, np.float32)))
    geom.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    geom.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    geom.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*points.min(axis=0)), Gf.Vec3f(*points.max(axis=0))]))
    image = texture_image(mesh)
    # a textured mesh carries both sides as faces of their own (twins): each shows from its own side only
    geom.CreateDoubleSidedAttr(image is None)
    material = UsdShade.Material.Define(stage, "/Root/Material")
    surface = UsdShade.Shader.Define(stage, "/Root/Material/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(1.0)
    surface.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    primvars = UsdGeom.PrimvarsAPI(geom)
    if image is not None:
        st = primvars.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
        st.Set(Vt.Vec2fArray.FromNumpy(np.asarray(mesh.visual.uv, np.float32)))
        image.save(folder / "texture.jpg", format="JPEG", quality=JPEG_QUALITY, subsampling=0)
        _usd_texture(stage, material, surface, "texture.jpg")
    elif mesh.visual.kind == "vertex":
        colours = np.asarray(mesh.visual.vertex_colors, np.float32)[:, :3] / 255.0
        display = primvars.CreatePrimvar("displayColor", Sdf.ValueTypeNames.Color3fArray, UsdGeom.Tokens.vertex)
        display.Set(Vt.Vec3fArray.FromNumpy(colours))
        reader = UsdShade.Shader.Define(stage, "/Root/Material/Colours")
        reader.CreateIdAttr("UsdPrimvarReader_float3")
        reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set("displayColor")
        surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
            reader.ConnectableAPI(), "result")
    UsdShade.MaterialBindingAPI.Apply(geom.GetPrim()).Bind(material)


def _usd_texture(stage, material, surface, file_name: str) -> None:
    from pxr import Sdf, UsdShade

    reader = UsdShade.Shader.Define(stage, "/Root/Material/UV")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set("st")
    texture = UsdShade.Shader.Define(stage, "/Root/Material/Texture")
    texture.CreateIdAttr("UsdUVTexture")
    texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(file_name)
    texture.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("sRGB")
    texture.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
    texture.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(texture.ConnectableAPI(), "rgb")
