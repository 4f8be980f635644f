"""Writing meshes for users: GLB for the web, PLY and OBJ for tools, all through trimesh.

GLB keeps the vertex colours (COLOR_0) and gets a double-sided material: an open surface shows its back
faces (the inside of a sleeve), which viewers cull by default (glTF 2.0 spec, material.doubleSided).
"""

from __future__ import annotations

from pathlib import Path

import trimesh
from trimesh.exchange.gltf import export_glb

SUFFIXES = (".glb", ".ply", ".obj")

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


def export_mesh(mesh: trimesh.Trimesh, path: str | Path) -> Path:
    """Write ``mesh`` to ``path``; the suffix picks the format (.glb, .ply, .obj). Returns the path.

    Raises ValueError for another suffix or a mesh without faces. Parent folders are created.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise ValueError(f"unknown mesh format {path.suffix or '(no suffix)'!r} for {path}: use {', '.join(SUFFIXES)}")
    if len(mesh.faces) == 0:
        raise ValueError("refusing to write a mesh with no faces")
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".glb":
        data = export_glb(mesh.scene(), include_normals=True, tree_postprocessor=_double_sided)
    elif suffix == ".ply":
        data = trimesh.exchange.ply.export_ply(mesh, encoding="binary", vertex_normal=True)
    else:
        data = trimesh.exchange.obj.export_obj(mesh, include_normals=True, include_color=True, include_texture=False)
    path.write_bytes(data if isinstance(data, bytes) else data.encode())
    return path
