"""Small test geometries built from quads (each quad its own surface), and a short refining
solve of a bundled scene."""
import numpy as np
import torch

import hemirad
from hemirad.assembly import make_solver
from hemirad.geometry.mesh import Mesh
from hemirad.scene.meshing import grid_quad


def quad(origin, u, v):
    """(4, 3) corners of the parallelogram origin + [0,1]u + [0,1]v; front side along u x v."""
    o, u, v = (np.asarray(x, dtype=np.float64) for x in (origin, u, v))
    return torch.tensor(np.stack([o, o + u, o + u + v, o + v]))


def quads_mesh(quads, element_sizes):
    """One Mesh from several quads, meshed at the given element sizes; material 0 for all."""
    parts = []
    for corners, size in zip(quads, element_sizes):
        vertices, triangles = grid_quad(corners, size)
        n = len(triangles)
        parts.append(Mesh(vertices, triangles, torch.zeros(n), torch.zeros(n), ["quad"]))
    return Mesh.concatenate(parts)


def closed_box(size=1.0, element_size=1.0):
    """The inside of a cube [0, size]^3: six quads with inward normals."""
    X, Y, Z = np.eye(3) * size
    o, s = np.zeros(3), np.full(3, size)
    faces = [quad(o, X, Y), quad(o, Z, X), quad(o, Y, Z),
             quad(s, -Y, -X), quad(s, -X, -Z), quad(s, -Z, -Y)]
    return quads_mesh(faces, [element_size] * 6)


def open_box(element_size=1.0):
    """``closed_box`` without its top (the face at y = 1, whose normal is -y): light escapes."""
    mesh = closed_box(element_size=element_size)
    rows = torch.nonzero(mesh.normals[:, 1] > -0.5).reshape(-1)
    return Mesh(mesh.vertices, mesh.triangles[rows], mesh.surface[rows], mesh.material[rows], mesh.surface_names)


def random_materials(T, seed, span, low, glowing, emission=(9.0, 5.0, 2.0)):
    """(rho, E), each (T, 3) float64: reflectances uniform in [low, low + span) from ``seed``,
    and the first ``glowing`` elements emitting ``emission``."""
    rho = torch.rand(T, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) * span + low
    E = torch.zeros(T, 3, dtype=torch.float64)
    E[:glowing] = torch.tensor(emission, dtype=torch.float64)
    return rho, E


def assert_power_balances(state, areas, reflectance, emission, emitted, rtol):
    """What reached the receivers' fronts, recovered from their radiosities (A (B - E) / rho,
    of which 1 - rho was absorbed), is the solver's absorbed power (to 1e-9), and absorbed +
    unshot + escaped = ``emitted`` (3,) to ``rtol``. ``areas``: (T,); the rest (T, 3)."""
    areas = areas[:, None]
    absorbed = ((1 - reflectance) / reflectance * (state.radiosity - emission) * areas).sum(0)
    unshot = (state.unshot * areas).sum(0)
    torch.testing.assert_close(absorbed, state.absorbed, rtol=1e-9, atol=0)
    torch.testing.assert_close(absorbed + unshot + state.escaped, emitted, rtol=rtol, atol=0)


def refined_solve(scene_name: str, shots: int, resolution: int = 64, **solver_options):
    """A pattern-2 refining solve of a bundled scene for ``shots`` shots; returns the
    finished (closed) ProgressiveSolver, with ``solver_options`` (cull, relabel, bound)
    passed on to ``make_solver``."""
    scene = hemirad.load_scene(scene_name)
    scene.refine.pattern, scene.refine.criterion = "pattern2", "gradient"
    scene.solver.resolution = resolution
    solver = make_solver(scene, **solver_options)
    try:
        solver.run(shots, 0.0)
    finally:
        solver.close()
    return solver


def assert_same_mesh(a, b):
    """Two meshes are the same, bit for bit: vertices, triangles, surfaces, materials, names."""
    for field in ("vertices", "triangles", "surface", "material"):
        assert torch.equal(getattr(a, field), getattr(b, field)), field
    assert a.surface_names == b.surface_names


def jittered_square(cells: int = 10, jitter: float = 0.3, seed: int = 0) -> Mesh:
    """The unit square in y = 0 (facing up), ``cells`` x ``cells`` squares each cut in two,
    its inner vertices moved at random by up to ``jitter`` of a cell: an irregular mesh."""
    n = cells + 1
    x, z = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    inner = (x > 0) & (x < 1) & (z > 0) & (z < 1)
    rng = np.random.default_rng(seed)
    x = x + inner * rng.uniform(-jitter, jitter, x.shape) / cells
    z = z + inner * rng.uniform(-jitter, jitter, z.shape) / cells
    vertices = np.stack([x.ravel(), np.zeros(n * n), z.ravel()], 1)
    i, j = np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij")
    a, b, c, d = (i * n + j).ravel(), ((i + 1) * n + j).ravel(), ((i + 1) * n + j + 1).ravel(), (i * n + j + 1).ravel()
    triangles = np.concatenate([np.stack([a, d, c], 1), np.stack([a, c, b], 1)])  # counter-clockwise from +y
    T = len(triangles)
    return Mesh(vertices, triangles, np.zeros(T, dtype=np.int64), np.zeros(T, dtype=np.int64))


def element_means(mesh: Mesh, f) -> torch.Tensor:
    """(T,) each element's exact mean of ``f`` (a quadratic of x, z): the mean of its values
    at the edges' midpoints, a rule exact for quadratics."""
    corners = mesh.corners
    mids = (corners + corners.roll(1, dims=1)) / 2  # (T, 3, 3)
    return f(mids[..., 0], mids[..., 2]).mean(1)
