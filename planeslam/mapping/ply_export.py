"""The map as two binary PLY files: the plane polygons coloured by object as a mesh
(map_planes.ply; each face with the `plane_id` and `object_id` of map.json, -1 for a
plane in no object), and the sparse cloud as a point cloud (map_points.ply)."""

from __future__ import annotations

import colorsys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from planeslam.mapping.contents import MapContents
from planeslam.mapping.sparse_cloud import GREY

_VERTEX = np.dtype(
    [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
)
_FACE = np.dtype([("n", "u1"), ("v", "<i4", (3,)), ("plane_id", "<i4"), ("object_id", "<i4")])


def plane_objects(contents: MapContents) -> dict[int, int]:
    """{plane id: object id}: a plane in several objects (a floor under a box) belongs to
    the object with the most plane area; -1 for planes in no object."""
    area = {o.id: sum(contents.planes[p].area_m2 for p in o.planes) for o in contents.objects}
    owner = dict.fromkeys(contents.planes, -1)
    for o in contents.objects:
        for p in o.planes:
            if owner.get(p, -1) < 0 or area[o.id] > area[owner[p]]:
                owner[p] = o.id
    return owner


def plane_colors(contents: MapContents) -> dict[int, np.ndarray]:
    """{plane id: (3,) uint8 colour}: one colour per object (`plane_objects`), grey for
    planes in no object."""
    return {p: GREY if o < 0 else _palette(o) for p, o in plane_objects(contents).items()}


@dataclass(frozen=True)
class PlaneMesh:
    """The map's plane polygons as triangles, world frame: each plane's outline as a fan
    about its mean vertex, coloured by object (`plane_colors`)."""

    vertices: np.ndarray
    """(V, 3) float64 [m]."""
    colors: np.ndarray
    """(V, 3) uint8 RGB."""
    triangles: np.ndarray
    """(F, 3) int64 vertex indices; every vertex is used by a face."""
    plane_ids: np.ndarray
    """(F,) int64 map plane id of each face."""
    object_ids: np.ndarray
    """(F,) int64 object id of each face's plane (`plane_objects`; -1: none)."""


def plane_mesh(contents: MapContents) -> PlaneMesh:
    """The map's plane polygons as a `PlaneMesh` (planes with fewer than 3 outline
    points are left out)."""
    colors = plane_colors(contents)
    objects = plane_objects(contents)
    verts, vcols, faces = [np.zeros((0, 3))], [np.zeros((0, 3), np.uint8)], [np.zeros((0, 3))]
    plane_ids: list[int] = []
    base = 0
    for p in contents.planes.values():
        ring = p.outline
        if len(ring) < 3:
            continue
        m = len(ring)
        verts.append(np.concatenate([ring, ring.mean(axis=0)[None]]))
        vcols.append(np.broadcast_to(colors[p.id], (m + 1, 3)))
        k = np.arange(m)
        faces.append(base + np.stack([np.full(m, m), k, (k + 1) % m], axis=1))
        plane_ids += [p.id] * m
        base += m + 1
    return PlaneMesh(
        vertices=np.concatenate(verts).astype(np.float64),
        colors=np.concatenate(vcols).astype(np.uint8),
        triangles=np.concatenate(faces).astype(np.int64),
        plane_ids=np.array(plane_ids, dtype=np.int64),
        object_ids=np.array([objects[p] for p in plane_ids], dtype=np.int64),
    )


def write_planes_ply(contents: MapContents, path: str | Path) -> Path:
    """The plane polygons (`plane_mesh`) as one binary little-endian PLY mesh; every vertex
    is used by a face, so cleaning tools (Open3D's `remove_unreferenced_vertices`,
    MeshLab) keep them all. Each face has int properties `plane_id` and `object_id` (the
    ids of map.json; -1: in no object). World frame [m]."""
    mesh = plane_mesh(contents)
    return _write_ply(
        path,
        mesh.vertices,
        mesh.colors,
        (mesh.triangles, mesh.plane_ids, mesh.object_ids),
        "planeslam map: plane polygons coloured by object (triangle fans), world frame",
    )


def write_points_ply(contents: MapContents, path: str | Path) -> Path:
    """The sparse non-planar cloud as one binary little-endian PLY point cloud (vertices
    with colours, no faces), world frame [m]."""
    return _write_ply(
        path,
        contents.cloud.points,
        contents.cloud.colors,
        None,
        "planeslam map: sparse cloud of what is not planar (voxel means), world frame",
    )


def _write_ply(
    path: str | Path,
    vertices: np.ndarray,
    colors: np.ndarray,
    faces: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    comment: str,
) -> Path:
    """(V, 3) float vertices [m] with (V, 3) uint8 colours and, for a mesh, (F, 3) vertex
    indices of triangles with (F,) plane and (F,) object ids (None: a point cloud, no face
    element)."""
    vrec = np.empty(len(vertices), dtype=_VERTEX)
    for name, col in zip(("x", "y", "z"), np.asarray(vertices).T, strict=True):
        vrec[name] = col
    for name, col in zip(("red", "green", "blue"), np.asarray(colors, np.uint8).T, strict=True):
        vrec[name] = col
    header = (
        f"ply\nformat binary_little_endian 1.0\ncomment {comment}\n"
        f"element vertex {len(vrec)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
    )
    frec = np.empty(0 if faces is None else len(faces[0]), dtype=_FACE)
    if faces is not None:
        frec["n"] = 3
        frec["v"], frec["plane_id"], frec["object_id"] = faces
        header += (
            f"element face {len(frec)}\nproperty list uchar int vertex_indices\n"
            "property int plane_id\nproperty int object_id\n"
        )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        fh.write((header + "end_header\n").encode("ascii"))
        fh.write(vrec.tobytes())
        fh.write(frec.tobytes())
    return path


def _palette(k: int) -> np.ndarray:
    """Distinct uint8 RGB colour for object index k (golden-ratio hues)."""
    r, g, b = colorsys.hsv_to_rgb((0.07 + 0.618034 * k) % 1.0, 0.75, 0.95)
    return np.array([round(255 * r), round(255 * g), round(255 * b)], dtype=np.uint8)
