"""The map as one binary PLY: plane polygons coloured by object, then the sparse cloud."""

from __future__ import annotations

import colorsys
from pathlib import Path

import numpy as np

from planeslam.mapping.contents import MapContents
from planeslam.mapping.sparse_cloud import GREY

_VERTEX = np.dtype(
    [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
)
_FACE = np.dtype([("n", "u1"), ("v", "<i4", (3,))])


def plane_colors(contents: MapContents) -> dict[int, np.ndarray]:
    """{plane id: (3,) uint8 colour}: one colour per object; a plane in several objects
    (a floor under a box) takes the colour of the object with the most plane area;
    grey for planes in no object."""
    area = {o.id: sum(contents.planes[p].area_m2 for p in o.planes) for o in contents.objects}
    colors = {pid: GREY for pid in contents.planes}
    owner: dict[int, int] = {}
    for o in contents.objects:
        for p in o.planes:
            if p not in owner or area[o.id] > area[owner[p]]:
                owner[p] = o.id
    for p, oid in owner.items():
        colors[p] = _palette(oid)
    return colors


def write_ply(contents: MapContents, path: str | Path) -> Path:
    """One binary little-endian PLY: each plane's outline as a triangle fan about its mean
    vertex, coloured by object (`plane_colors`), followed by the sparse cloud as
    unreferenced vertices with their colours. Open3D reads it as a TriangleMesh
    (read_triangle_mesh) or as a point cloud of all vertices (read_point_cloud)."""
    colors = plane_colors(contents)
    verts, vcols, faces = [], [], []
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
        base += m + 1
    verts.append(contents.cloud.points)
    vcols.append(contents.cloud.colors)
    v = np.concatenate(verts)
    c = np.concatenate(vcols).astype(np.uint8)
    f = np.concatenate(faces) if faces else np.zeros((0, 3), dtype=np.int64)
    vrec = np.empty(len(v), dtype=_VERTEX)
    for name, col in zip(("x", "y", "z"), v.T, strict=True):
        vrec[name] = col
    for name, col in zip(("red", "green", "blue"), c.T, strict=True):
        vrec[name] = col
    frec = np.empty(len(f), dtype=_FACE)
    frec["n"] = 3
    frec["v"] = f
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        "comment planeslam map: plane polygons coloured by object, then the sparse cloud\n"
        f"element vertex {len(v)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(vrec.tobytes())
        fh.write(frec.tobytes())
    return path


def _palette(k: int) -> np.ndarray:
    """Distinct uint8 RGB colour for object index k (golden-ratio hues)."""
    r, g, b = colorsys.hsv_to_rgb((0.07 + 0.618034 * k) % 1.0, 0.75, 0.95)
    return np.array([round(255 * r), round(255 * g), round(255 * b)], dtype=np.uint8)
