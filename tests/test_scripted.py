"""The kernels compiled by TorchScript (``core.scripted``) give the plain functions' numbers
bit for bit, their gradients included, and a kernel that cannot compile still runs."""
import importlib
import pkgutil

import numpy as np
import pytest
import torch

import hemirad
from hemirad.assembly import NEAR_REACH
from hemirad.core.scripted import scripted
from hemirad.geometry import analytic
from hemirad.geometry.analytic import point_to_triangles
from hemirad.geometry.patches import build_patches
from hemirad.transport.shooters import PatchShooters
from hemirad.transport.solver import ProgressiveSolver

from patches import open_box, random_materials


def modules():
    """The package's modules (not its command line, ``__main__``)."""
    return [importlib.import_module(info.name) for info in pkgutil.walk_packages(hemirad.__path__, "hemirad.")
            if not info.name.endswith("__main__")]


def kernels() -> dict[str, object]:
    """Every ``scripted`` kernel in the package, by module and name."""
    return {f"{module.__name__}.{name}": value for module in modules() for name, value in vars(module).items()
            if callable(value) and hasattr(value, "eager") and getattr(value, "__module__", None) == module.__name__}


def test_every_kernel_compiles():
    # a kernel that stopped compiling (a global, an unsupported call) would fall back to the
    # plain function silently, the same numbers at the old speed: caught here
    found = kernels()
    assert len(found) >= 7
    assert [name for name, kernel in found.items() if not kernel.is_scripted()] == []


def eager_everywhere(monkeypatch):
    """Every kernel, wherever it was imported, replaced by its plain function."""
    for module in modules():
        for name, value in list(vars(module).items()):
            if callable(value) and hasattr(value, "eager"):
                monkeypatch.setattr(module, name, value.eager)


def triangles(count: int, seed: int, offset: float = 0.0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(count, 3, 3, dtype=torch.float64, generator=g) + offset


def contour_and_lambert_factors() -> list[torch.Tensor]:
    sources, receivers = triangles(600, 0), triangles(600, 1, 0.3)
    receivers[:200] = sources[:200].roll(1, 1) * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)  # pairs that touch
    point = torch.tensor([0.4, 0.2, 0.1], dtype=torch.float64)
    normal = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    corners = triangles(800, 2, -0.3)  # many cut by the point's tangent plane
    points = corners.mean(1, keepdim=True) + 0.05
    normals = torch.nn.functional.normalize(triangles(800, 3)[:, :1], dim=2)
    return [analytic.triangle_to_triangles(sources, receivers, 4),
            analytic.triangle_to_triangles(sources, receivers, 5, pieces=False),
            analytic.point_to_triangles(point, normal, corners), analytic.point_to_triangles(points, normals, corners)]


def test_the_contour_integrals_and_lamberts_factor_are_the_plain_functions_bit_for_bit(monkeypatch):
    made = contour_and_lambert_factors()
    assert all(bool((f > 0).any()) for f in made)
    eager_everywhere(monkeypatch)
    for scripted_factors, eager_factors in zip(made, contour_and_lambert_factors()):
        assert torch.equal(scripted_factors, eager_factors)


def test_a_call_autograd_records_takes_the_plain_functions_gradient():
    corners = triangles(300, 4, -0.3)
    normal = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    gradients = []
    for function in (point_to_triangles, point_to_triangles.eager):
        point = torch.tensor([0.4, 0.2, 0.1], dtype=torch.float64, requires_grad=True)
        function(point, normal, corners).sum().backward()
        gradients.append(point.grad)
    assert torch.equal(*gradients) and bool(gradients[0].abs().sum() > 0)


def open_box_solve():
    # patches shooting in sweeps with near fields (contour integrals, small receivers' factors
    # from points) and every sub-pixel receiver's factor from visibility samples
    mesh = open_box(element_size=0.125)
    rho, E = random_materials(mesh.num_elements, seed=3, span=0.6, low=0.2, glowing=6)
    shooters = PatchShooters(build_patches(mesh, np.full(mesh.num_elements, 0.5)), torch.device("cpu"))
    solver = ProgressiveSolver(mesh, rho, E, 16, patches=shooters, near_reach=NEAR_REACH, sweeps=True,
                               small_receivers="closed_form")
    try:
        return solver.run(max_shots=4000, unshot_fraction=1e-4).radiosity.clone()
    finally:
        solver.close()


def test_a_solve_gives_the_same_numbers_with_every_kernel_eager(monkeypatch):
    scripted_answer = open_box_solve()
    eager_everywhere(monkeypatch)
    assert torch.equal(scripted_answer, open_box_solve())


def test_a_kernel_that_cannot_compile_runs_as_the_plain_function():
    limit = 0.5

    def clipped(x: torch.Tensor) -> torch.Tensor:
        return x.clamp(max=limit)  # a closed-over float: TorchScript refuses it

    kernel = scripted(clipped)
    x = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    assert not kernel.is_scripted()
    assert torch.equal(kernel(x), x.clamp(max=0.5))


@pytest.mark.parametrize("requires_grad", [False, True])
def test_a_kernel_that_compiles_runs_scripted_and_keeps_its_numbers(requires_grad):
    def scaled(x: torch.Tensor, factor: float) -> torch.Tensor:
        return (x * factor).sin() / (1.0 + x * x)

    kernel = scripted(scaled)
    x = torch.linspace(-2.0, 2.0, 101, dtype=torch.float64, requires_grad=requires_grad)
    assert kernel.is_scripted()
    assert torch.equal(kernel(x, 3.0), scaled(x, 3.0))
