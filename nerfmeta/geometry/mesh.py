"""Triangle meshes: a typed container, PLY out (binary or ASCII, atomic), PLY and OBJ in, surface sampling.

The PLY written here is the common "vertex x y z [nx ny nz] [red green blue]; face vertex_indices"
layout that MeshLab, Open3D and trimesh read. The reader takes what this writer writes and the
ordinary variants (ASCII or binary little/big endian, float/double coordinates, any int type for
the face lists, extra vertex properties skipped); OBJ: ``v`` and ``f`` lines (polygons fanned into
triangles, ``v/vt/vn`` indices and negative indices allowed).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nerfmeta.errors import ConfigError
from nerfmeta.io import atomic_path

PLY_TYPES = {"char": "i1", "uchar": "u1", "short": "i2", "ushort": "u2", "int": "i4", "uint": "u4", "float": "f4",
             "double": "f8", "int8": "i1", "uint8": "u1", "int16": "i2", "uint16": "u2", "int32": "i4", "uint32": "u4",
             "float32": "f4", "float64": "f8"}


@dataclass
class Mesh:
    """A triangle mesh.

    Attributes:
        vertices: (V, 3) float64 positions.
        faces: (F, 3) int64 vertex indices, counter-clockwise seen from outside.
        colors: (V, 3) uint8 RGB per vertex, or None.
        normals: (V, 3) float64 unit outward normals per vertex, or None.
    """

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray | None = None
    normals: np.ndarray | None = None

    def face_normals_and_areas(self) -> tuple[np.ndarray, np.ndarray]:
        """(F, 3) unit face normals (right-hand rule) and (F,) face areas."""
        a, b, c = (self.vertices[self.faces[:, k]] for k in range(3))
        cross = np.cross(b - a, c - a)
        norm = np.linalg.norm(cross, axis=1)
        return cross / np.maximum(norm, 1e-300)[:, None], 0.5 * norm

    def transformed(self, scale: float, offset: np.ndarray) -> "Mesh":
        """The mesh with every vertex mapped to ``(v - offset) / scale`` (undoing a load-time normalisation)."""
        return Mesh((self.vertices - offset) / scale, self.faces, self.colors, self.normals)


def write_ply(path: str | os.PathLike, mesh: Mesh, *, binary: bool = True) -> None:
    """Write ``mesh`` as PLY (binary little endian or ASCII), atomically (a temporary file renamed onto ``path``)."""
    v = np.asarray(mesh.vertices, dtype=np.float32)
    f = np.asarray(mesh.faces, dtype=np.int32)
    props = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    if mesh.normals is not None:
        props += [("nx", "f4"), ("ny", "f4"), ("nz", "f4")]
    if mesh.colors is not None:
        props += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    names = {"f4": "float", "u1": "uchar"}
    header = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0", "comment written by nerfmeta",
              f"element vertex {len(v)}", *[f"property {names[t]} {n}" for n, t in props],
              f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    vert = np.zeros(len(v), dtype=[(n, "<" + t) for n, t in props])
    for k, axis in enumerate("xyz"):
        vert[axis] = v[:, k]
    if mesh.normals is not None:
        for k, axis in enumerate(("nx", "ny", "nz")):
            vert[axis] = mesh.normals[:, k]
    if mesh.colors is not None:
        for k, channel in enumerate(("red", "green", "blue")):
            vert[channel] = mesh.colors[:, k]
    face = np.zeros(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face["n"], face["i"] = 3, f
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as out:
            out.write(("\n".join(header) + "\n").encode("ascii"))
            if binary:
                out.write(vert.tobytes())
                out.write(face.tobytes())
            else:
                for row in vert:
                    out.write((" ".join(_ascii(x) for x in row) + "\n").encode("ascii"))
                for tri in f:
                    out.write(f"3 {tri[0]} {tri[1]} {tri[2]}\n".encode("ascii"))


def _ascii(x: object) -> str:
    return repr(float(x)) if isinstance(x, (float, np.floating)) else str(int(x))  # type: ignore[call-overload]


def read_mesh(path: str | os.PathLike) -> Mesh:
    """Read a PLY or OBJ triangle mesh (one-line :class:`ConfigError` naming the file otherwise)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such mesh file")
    suffix = path.suffix.lower()
    if suffix == ".ply":
        return _read_ply(path)
    if suffix == ".obj":
        return _read_obj(path)
    raise ConfigError(f"{path}: not a mesh file nerfmeta reads (use .ply or .obj)")


def _read_obj(path: Path) -> Mesh:
    verts, faces = [], []
    for line in path.read_text(errors="replace").splitlines():
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "v":
            verts.append([float(x) for x in parts[1:4]])
        elif parts[0] == "f":
            idx = [int(p.split("/")[0]) for p in parts[1:]]
            idx = [i - 1 if i > 0 else len(verts) + i for i in idx]
            faces += [[idx[0], idx[k], idx[k + 1]] for k in range(1, len(idx) - 1)]
    if not verts or not faces:
        raise ConfigError(f"{path}: an OBJ without vertices or faces")
    return Mesh(np.array(verts, dtype=np.float64), np.array(faces, dtype=np.int64))


def _read_ply(path: Path) -> Mesh:
    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ConfigError(f"{path}: not a PLY file (no 'ply' ... 'end_header' header)")
    body_start = data.index(b"\n", end) + 1
    header = data[:end].decode("ascii", errors="replace").splitlines()
    fmt, elements = "ascii", []  # elements: [name, count, [(prop, dtype or (count_t, item_t))]]
    for line in header:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            elements.append([parts[1], int(parts[2]), []])
        elif parts[0] == "property" and elements:
            if parts[1] == "list":
                elements[-1][2].append((parts[4], (PLY_TYPES[parts[2]], PLY_TYPES[parts[3]])))
            else:
                elements[-1][2].append((parts[2], PLY_TYPES[parts[1]]))
    try:
        if fmt == "ascii":
            values = {name: rows for name, rows in _ply_ascii(data[body_start:], elements)}
        else:
            endian = "<" if fmt == "binary_little_endian" else ">"
            values = {name: rows for name, rows in _ply_binary(data[body_start:], elements, endian)}
        vert, faces = values["vertex"], values["face"]
    except (KeyError, ValueError, IndexError) as err:
        raise ConfigError(f"{path}: unreadable PLY ({err})") from None
    vertices = np.stack([np.asarray(vert[a], dtype=np.float64) for a in "xyz"], -1)
    colors = None
    if all(c in vert for c in ("red", "green", "blue")):
        colors = np.stack([np.asarray(vert[c]) for c in ("red", "green", "blue")], -1).astype(np.uint8)
    tris = [[poly[0], poly[k], poly[k + 1]] for poly in faces["vertex_indices" if "vertex_indices" in faces else "vertex_index"]
            for k in range(1, len(poly) - 1)]
    return Mesh(vertices, np.array(tris, dtype=np.int64).reshape(-1, 3), colors)


def _ply_ascii(body: bytes, elements: list) -> list[tuple[str, dict[str, list]]]:
    tokens = body.split()
    pos, out = 0, []
    for name, count, props in elements:
        cols: dict[str, list] = {p: [] for p, _ in props}
        for _ in range(count):
            for prop, kind in props:
                if isinstance(kind, tuple):
                    n = int(tokens[pos])
                    cols[prop].append([int(t) for t in tokens[pos + 1: pos + 1 + n]])
                    pos += 1 + n
                else:
                    cols[prop].append(float(tokens[pos]))
                    pos += 1
        out.append((name, cols))
    return out


def _ply_binary(body: bytes, elements: list, endian: str) -> list[tuple[str, dict[str, list]]]:
    pos, out = 0, []
    for name, count, props in elements:
        if all(not isinstance(kind, tuple) for _, kind in props):
            dtype = np.dtype([(p, endian + k) for p, k in props])
            rows = np.frombuffer(body, dtype=dtype, count=count, offset=pos)
            pos += dtype.itemsize * count
            out.append((name, {p: rows[p] for p, _ in props}))
            continue
        cols: dict[str, list] = {p: [] for p, _ in props}
        for _ in range(count):  # rows with lists: one at a time (faces of other writers)
            for prop, kind in props:
                if isinstance(kind, tuple):
                    n_t, item_t = np.dtype(endian + kind[0]), np.dtype(endian + kind[1])
                    n = int(np.frombuffer(body, n_t, 1, pos)[0])
                    pos += n_t.itemsize
                    cols[prop].append(np.frombuffer(body, item_t, n, pos).tolist())
                    pos += item_t.itemsize * n
                else:
                    t = np.dtype(endian + kind)
                    cols[prop].append(np.frombuffer(body, t, 1, pos)[0])
                    pos += t.itemsize
        out.append((name, cols))
    return out


def sample_surface(mesh: Mesh, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points drawn uniformly by area on the mesh, with their face normals: (n, 3) and (n, 3)."""
    normals, areas = mesh.face_normals_and_areas()
    if len(areas) == 0 or areas.sum() <= 0:
        raise ConfigError("the mesh has no area to sample points on")
    face = rng.choice(len(areas), size=n, p=areas / areas.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    a, b, c = (mesh.vertices[mesh.faces[face, k]] for k in range(3))
    return a + u[:, None] * (b - a) + v[:, None] * (c - a), normals[face]


@dataclass(frozen=True)
class MeshTopology:
    """Connected components of a triangle mesh and their genus (from the Euler characteristic).

    Attributes:
        components: number of connected components (sharing vertices).
        faces: (components,) faces per component, largest first.
        genus: (components,) genus per component with each boundary loop closed by a disc,
            ``(2 - (V - E + F) - loops) / 2`` (a sphere 0, a torus or a mug with a handle 1). A marching-cubes
            mesh of a field is open only where its surface leaves the meshed box; closing each such cut by a
            disc is closing the solid along the box, so a bulge through a box face does not count as a handle.
        boundary_edges: edges with one face (0 for a closed mesh).
        boundary_loops: loops those edges form (connected sets of boundary edges), all components together.
        nonmanifold_edges: edges with more than two faces.
    """

    components: int
    faces: tuple[int, ...]
    genus: tuple[float, ...]
    boundary_edges: int
    nonmanifold_edges: int
    boundary_loops: int = 0

    def main(self, min_fraction: float = 0.01) -> tuple[int, float]:
        """Components holding at least ``min_fraction`` of the faces, and their total genus (floaters left out)."""
        total = sum(self.faces)
        kept = [g for f, g in zip(self.faces, self.genus) if f >= min_fraction * total]
        return len(kept), float(sum(kept))


def mesh_topology(mesh: Mesh) -> MeshTopology:
    """Components, genus per component (boundary loops closed) and open/non-manifold edge counts of ``mesh``
    (vertices welded by index)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    faces = np.asarray(mesh.faces, dtype=np.int64)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    n = len(mesh.vertices)
    graph = coo_matrix((np.ones(len(unique)), (unique[:, 0], unique[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    used = np.unique(faces)
    comp_ids, comp_of_used = np.unique(label[used], return_inverse=True)
    index = {int(c): i for i, c in enumerate(comp_ids)}
    k = len(comp_ids)
    v_count = np.bincount(comp_of_used, minlength=k)
    e_count = np.bincount([index[int(c)] for c in label[unique[:, 0]]], minlength=k) if len(unique) else np.zeros(k, int)
    f_count = np.bincount([index[int(c)] for c in label[faces[:, 0]]], minlength=k) if len(faces) else np.zeros(k, int)
    loops = _boundary_loops(unique[counts == 1], label, index, k)
    genus = (2 - (v_count - e_count + f_count) - loops) / 2.0
    order = np.argsort(-f_count, kind="stable")
    return MeshTopology(k, tuple(int(f_count[i]) for i in order), tuple(float(genus[i]) for i in order),
                        int((counts == 1).sum()), int((counts > 2).sum()), int(loops.sum()))


def _boundary_loops(boundary: np.ndarray, label: np.ndarray, index: dict[int, int], k: int) -> np.ndarray:
    """(k,) loops of boundary edges (B, 2) per mesh component: connected sets of boundary edges."""
    if len(boundary) == 0:
        return np.zeros(k, dtype=np.int64)
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    verts, local = np.unique(boundary, return_inverse=True)
    local = local.reshape(-1, 2)
    graph = coo_matrix((np.ones(len(local)), (local[:, 0], local[:, 1])), shape=(len(verts), len(verts)))
    _, loop_of = connected_components(graph, directed=False)
    _, first = np.unique(loop_of, return_index=True)  # one vertex of each loop names its mesh component
    return np.bincount([index[int(label[v])] for v in verts[first]], minlength=k)
