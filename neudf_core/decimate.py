"""Quadric decimation to a face count, open boundaries kept where they are (pyfqmr).

A mesh from a distance field is dense (a marching-cubes grid of 256 gives hundreds of thousands of faces)
where a viewer or a phone wants about a hundred thousand. pyfqmr's quadric simplification with
``preserve_border`` never moves or removes a vertex of an open boundary, so sleeves, hems and holes keep
their rims; the interior takes the reduction. The vertex colours are carried over from the dense mesh
(the colour at the closest point of its surface).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # loaded when a mesh is decimated: the API process reads only DEFAULT_FACES
    import trimesh

__all__ = ["DEFAULT_FACES", "MIN_FACES", "decimate", "transfer_vertex_colors"]

DEFAULT_FACES = 100_000
MIN_FACES = 100  # a target below this shows nothing: 0 (keep every face) is the way to turn decimation off


def decimate(mesh: trimesh.Trimesh, faces: int = DEFAULT_FACES) -> trimesh.Trimesh:
    """``mesh`` with about ``faces`` faces (at least as many as its boundary needs), vertex colours kept.

    A mesh at or below ``faces`` (or ``faces`` <= 0) comes back as it is. The metadata is kept, with
    ``decimation: {faces_before, faces_after}`` added.
    """
    if faces <= 0 or len(mesh.faces) <= faces:
        return mesh
    import pyfqmr
    import trimesh

    simplifier = pyfqmr.Simplify()
    simplifier.setMesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int32))
    # aggressiveness 7 is the library's default; a lower one spends more iterations for a lower error
    simplifier.simplify_mesh(target_count=int(faces), aggressiveness=5, preserve_border=True, verbose=False)
    vertices, new_faces, _ = simplifier.getMesh()
    out = trimesh.Trimesh(vertices, new_faces, process=False)
    out.remove_unreferenced_vertices()
    if mesh.visual.kind == "vertex":
        transfer_vertex_colors(mesh, out)
    out.metadata.update(mesh.metadata)
    out.metadata["decimation"] = {"faces_before": int(len(mesh.faces)), "faces_after": int(len(out.faces))}
    return out


def transfer_vertex_colors(source: trimesh.Trimesh, target: trimesh.Trimesh) -> None:
    """Colour ``target``'s vertices with ``source``'s vertex colours at the closest point of its surface."""
    import open3d as o3d  # heavy import, only needed here

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(source.vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(source.faces, np.uint32)))
    result = scene.compute_closest_points(o3d.core.Tensor(np.asarray(target.vertices, np.float32)))
    face = result["primitive_ids"].numpy().astype(np.int64)
    uv = result["primitive_uvs"].numpy().astype(np.float64)
    bary = np.stack([1.0 - uv.sum(axis=1), uv[:, 0], uv[:, 1]], axis=1)
    colors = np.asarray(source.visual.vertex_colors, np.float64)[np.asarray(source.faces)[face]]
    target.visual.vertex_colors = np.einsum("nk,nkc->nc", bary, colors).round().clip(0, 255).astype(np.uint8)
