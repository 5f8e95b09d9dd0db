"""Meshes: PLY/OBJ round trips, marching cubes orientation, the scene file's frame, the mesh command."""

import types

import numpy as np
import pytest
import torch

from nerfmeta.data.scene import Normalization
from nerfmeta.errors import ConfigError
from nerfmeta.fields.registry import build_model
from nerfmeta.fields.sdf import SdfConfig
from nerfmeta.geometry.extract import marching_cubes, surface_function
from nerfmeta.geometry.mesh import Mesh, mesh_topology, read_mesh, write_ply
from nerfmeta.geometry.runs import mesh_in_file_frame

TETRA = Mesh(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]), np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]),
             np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [10, 20, 30]], dtype=np.uint8))


@pytest.mark.parametrize("binary", [True, False])
def test_ply_round_trip(tmp_path, binary):
    write_ply(tmp_path / "t.ply", TETRA, binary=binary)
    back = read_mesh(tmp_path / "t.ply")
    assert np.allclose(back.vertices, TETRA.vertices) and np.array_equal(back.faces, TETRA.faces)
    assert np.array_equal(back.colors, TETRA.colors)
    assert not list(tmp_path.glob(".*tmp"))  # atomic: no temporary file left


def test_obj_with_quads_and_slashes(tmp_path):
    (tmp_path / "q.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//1 4//1\n")
    mesh = read_mesh(tmp_path / "q.obj")
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3]]
    assert mesh.face_normals_and_areas()[1].sum() == pytest.approx(1.0)


def test_unreadable_mesh_is_a_config_error(tmp_path):
    (tmp_path / "x.ply").write_bytes(b"not a ply")
    with pytest.raises(ConfigError, match="x.ply"):
        read_mesh(tmp_path / "x.ply")


@pytest.mark.parametrize("inside_above", [False, True])
def test_marching_cubes_sphere_faces_point_outward(inside_above):
    n = 24
    axis = np.linspace(-1, 1, n)
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    r = np.sqrt(x**2 + y**2 + z**2)
    values = (-(r - 0.6) if inside_above else r - 0.6).astype(np.float32)
    mesh = marching_cubes(values, np.array([[-1.0] * 3, [1.0] * 3]), 0.0, inside_above)
    assert np.abs(np.linalg.norm(mesh.vertices, axis=1) - 0.6).max() < 2.0 / (n - 1)
    face_n, _ = mesh.face_normals_and_areas()
    centres = mesh.vertices[mesh.faces].mean(1)
    assert (np.sum(face_n * centres, axis=1) > 0).all()
    assert (np.sum(mesh.normals * mesh.vertices, axis=1) > 0).all()  # vertex normals point outward too


def lattice_mesh(sdf, n: int = 40) -> Mesh:
    axis = np.linspace(-1, 1, n)
    p = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1)
    return marching_cubes(sdf(p).astype(np.float32), np.array([[-1.0] * 3, [1.0] * 3]), 0.0, False)


def test_topology_counts_components_and_handles():
    """A sphere has genus 0, a torus (a mug's handle) 1, two balls are two components; a tetrahedron is closed."""
    def sphere(p, c=(0.0, 0.0, 0.0), r=0.5):
        return np.linalg.norm(p - np.array(c), axis=-1) - r

    def torus(p):
        return np.hypot(np.hypot(p[..., 0], p[..., 1]) - 0.55, p[..., 2]) - 0.2

    one, ring = mesh_topology(lattice_mesh(sphere)), mesh_topology(lattice_mesh(torus))
    two = mesh_topology(lattice_mesh(lambda p: np.minimum(sphere(p, (-0.5, 0, 0), 0.3), sphere(p, (0.5, 0, 0), 0.3))))
    assert (one.components, one.genus, one.boundary_edges) == (1, (0.0,), 0)
    assert (ring.components, ring.genus, ring.boundary_edges) == (1, (1.0,), 0)
    assert two.components == 2 and two.genus == (0.0, 0.0) and two.main() == (2, 0.0)
    tetra = mesh_topology(TETRA)
    assert (tetra.components, tetra.faces, tetra.genus, tetra.boundary_edges, tetra.nonmanifold_edges) == (1, (4,), (0.0,), 0, 0)
    opened = mesh_topology(Mesh(TETRA.vertices, TETRA.faces[:3]))
    assert (opened.boundary_edges, opened.boundary_loops, opened.genus) == (3, 1, (0.0,))  # a disc, closed: a sphere


def test_surfaces_cut_by_the_box_are_closed_along_it():
    """A marching-cubes mesh opens where the surface leaves the box: each cut counts as closed by a disc, so a
    torus whose rim pokes through a face keeps genus 1, and one cut across its tube (a C-shaped solid) has 0."""
    def torus_at(cx):
        return lambda p: np.hypot(np.hypot(p[..., 0] - cx, p[..., 1]) - 0.55, p[..., 2]) - 0.2

    poked, cut = mesh_topology(lattice_mesh(torus_at(0.3))), mesh_topology(lattice_mesh(torus_at(0.8)))
    assert poked.boundary_edges > 0 and (poked.components, poked.boundary_loops, poked.genus) == (1, 1, (1.0,))
    assert (cut.components, cut.boundary_loops, cut.genus) == (1, 2, (0.0,))


def test_small_floaters_are_left_out_of_the_main_topology():
    tiny = mesh_topology(lattice_mesh(lambda p: np.minimum(np.linalg.norm(p, axis=-1) - 0.7,
                                                               np.linalg.norm(p - 0.9, axis=-1) - 0.06)))
    assert tiny.components == 2 and tiny.faces[0] > 100 * tiny.faces[1]
    assert tiny.main() == (1, 0.0)


def test_mesh_is_in_the_scene_files_frame_with_colours():
    """The SDF's initial sphere (radius 0.5 half-sides) comes back through the scene's normalisation, undone."""
    bounds = torch.tensor([[-2.0] * 3, [2.0] * 3])  # loaded frame
    model = build_model("sdf", SdfConfig(depth=2, width=64), bounds, seed=0)
    scene = types.SimpleNamespace(bounds=bounds, normalization=Normalization(scale=4.0, offset=(1.0, 0.0, 0.0)))
    mesh = mesh_in_file_frame(model, scene, 32)
    loaded = mesh.vertices * 4.0 + np.array([1.0, 0.0, 0.0])
    sdf = model.sdf_world(torch.as_tensor(loaded, dtype=torch.float32)).detach().numpy()
    assert np.abs(sdf).max() < 0.1  # on the field's zero set, in the loaded frame
    assert mesh.colors.shape == (len(mesh.vertices), 3) and mesh.colors.dtype == np.uint8


def test_density_backbones_mesh_at_a_documented_threshold():
    from nerfmeta.fields.nerf_mlp import NerfMLPConfig

    box = torch.tensor([[-1.0] * 3, [1.0] * 3])
    model = build_model("nerf", NerfMLPConfig(depth=1, width=8, skips=()), box, seed=0)
    surface = surface_function(model, box)
    assert surface.kind == "density" and surface.inside_above
    assert surface.level == pytest.approx(np.log(2) / (0.01 * np.sqrt(12.0)))


def test_mesh_cli_refuses_to_overwrite_and_writes_a_readable_ply(tiny_scene, tmp_path, capsys):
    from nerfmeta.cli import main

    run = tmp_path / "run"
    assert main(["fit", str(tiny_scene), "--out", str(run), "--backbone", "sdf", "--iters", "1", "--batch-rays", "32",
                 "--renders", "0", "--eval-views", "1", "--set", "depth=2", "--set", "width=32", "--set", "n_samples=8"]) == 0
    out = tmp_path / "m.ply"
    assert main(["mesh", str(run), "--out", str(out), "--resolution", "24", "--ascii"]) == 0
    mesh = read_mesh(out)
    assert len(mesh.faces) > 100 and mesh.colors is not None
    capsys.readouterr()
    assert main(["mesh", str(run), "--out", str(out), "--resolution", "24"]) == 2
    assert "--overwrite" in capsys.readouterr().err


class DeviceProbe(torch.nn.Module):
    """A field whose weights live on the ``meta`` device (a stand-in for a GPU, which tests cannot count on);
    it records the device of every input and answers with zeros on the CPU."""

    def __init__(self, sdf: bool):
        super().__init__()
        self.weight = torch.nn.Parameter(torch.empty(1, device="meta"))
        self.seen: set[str] = set()
        if sdf:
            self.sdf_world = self._zeros

    def _zeros(self, *inputs):
        self.seen.update(x.device.type for x in inputs if isinstance(x, torch.Tensor))
        return torch.zeros(len(inputs[0]))

    def get_density(self, points):
        return self._zeros(points), None

    def get_outputs(self, embedding, t, dirs, ray_idx):
        self._zeros(dirs, ray_idx)
        return torch.zeros(len(dirs), 3)


@pytest.mark.parametrize("sdf", [True, False])
def test_surfaces_and_colours_are_read_on_the_fields_device(sdf):
    """Points made on the CPU (lattices, mesh vertices) reach a field on another device there (a CUDA fit's
    summary and 'nerfmeta mesh' of a CUDA run failed with 'Expected all tensors to be on the same device')."""
    from nerfmeta.geometry.extract import vertex_colors

    probe = DeviceProbe(sdf)
    values = surface_function(probe, torch.tensor([[-1.0] * 3, [1.0] * 3])).values(torch.rand(5, 3))
    assert values.device.type == "cpu" and probe.seen == {"meta"}
    probe.seen.clear()
    mesh = Mesh(TETRA.vertices, TETRA.faces, None, TETRA.vertices.copy())
    assert vertex_colors(probe, mesh).shape == (4, 3) and probe.seen == {"meta"}
