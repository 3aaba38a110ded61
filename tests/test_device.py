"""Where a solve runs: every tensor on the solver's device, CUDA only when asked for and there.

No CI machine has a GPU: the CUDA comparison runs where PyTorch sees one and is skipped
elsewhere. What every machine checks is that the solver never makes a tensor on the default
device instead of its own: with the default device set to ``meta`` (tensors with no data),
any such tensor fails the first operation that mixes it with real ones, as a CPU tensor
would fail beside CUDA ones.
"""
from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest
import torch

import hemirad
from hemirad.adaptive.refine import Refiner
from hemirad.core.device import select_device
from hemirad.core.errors import HemiradInputError
from hemirad.core.fastops import device_forms
from hemirad.scene.meshing import build_mesh
from hemirad.transport.solver import ProgressiveSolver

CUDA = torch.cuda.is_available()


# thresholds that refine a few levels deep in a few shots, well inside the element budget
THRESHOLDS = {"gradient": 1e-3, "receiver": 1e-3, "partial_visibility": 1e-4, "neighbor_difference": 4e-3}


def refining_solve(criterion: str, device: str = "cpu", shots: int = 6, default_device: str | None = None) -> dict:
    """A few refining shots on ``floating`` at hemicube 32; the solver's ``state_dict``.
    ``default_device``: the process's default torch device while the solver works."""
    scene = hemirad.load_scene("floating")
    scene.refine.pattern, scene.refine.criterion, scene.refine.threshold = "pattern2", criterion, THRESHOLDS[criterion]
    mesh = build_mesh(scene.with_element_sizes_scaled(2.0))
    reflectance = scene.reflectance_table()[mesh.material]
    emission = scene.emission_table()[mesh.material]
    with torch.device(default_device or device):
        solver = ProgressiveSolver(mesh, reflectance, emission, 32, Refiner(scene.refine, emission), device=device)
        try:
            solver.run(shots, 0.0)
            return solver.state_dict()
        finally:
            solver.close()


@pytest.mark.parametrize("criterion", sorted(THRESHOLDS))
def test_a_refining_solve_makes_no_tensor_on_the_default_device(criterion):
    expected = refining_solve(criterion)
    assert int(expected["mesh"]["level"].max()) >= 2  # it refined, twice over somewhere
    got = refining_solve(criterion, default_device="meta")
    for key in ("radiosity", "unshot", "absorbed", "escaped"):
        assert got[key].device.type == "cpu" and torch.equal(got[key], expected[key]), key
    assert torch.equal(got["mesh"]["triangles"], expected["mesh"]["triangles"])


@pytest.mark.parametrize("criterion", sorted(THRESHOLDS))
def test_the_device_forms_of_the_fast_idioms_give_the_same_solve(criterion):
    # What a CUDA solve runs in place of the NumPy forms CPU tensors take (fastops.py):
    # checked here on the CPU, bit for bit, so that a GPU machine only adds the device.
    expected = refining_solve(criterion)
    with device_forms():
        got = refining_solve(criterion)
    for key in ("radiosity", "unshot", "absorbed", "escaped"):
        assert torch.equal(got[key], expected[key]), key
    assert torch.equal(got["mesh"]["triangles"], expected["mesh"]["triangles"])


def test_device_names():
    assert select_device("cpu") == torch.device("cpu")
    assert select_device("auto") == torch.device("cuda" if CUDA else "cpu")
    with pytest.raises(HemiradInputError, match="expected one of cpu, cuda, cuda:N, auto"):
        select_device("gpu")
    with pytest.raises(HemiradInputError, match="CUDA device"):
        select_device("cuda:99")


@pytest.mark.skipif(CUDA, reason="this machine has CUDA")
def test_cuda_asked_for_without_one_is_a_clear_error(tmp_path, capsys):
    from hemirad.cli import main

    assert main(["cornell_box", "--device", "cuda", "--shots", "2", "-o", str(tmp_path), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert "PyTorch sees no CUDA device" in err and "--device cpu" in err and "\n" not in err
    assert not (tmp_path / "stats.json").exists()


# In a fresh process: the GPU's OpenGL context must be the process's first.
_CUDA_AGAINST_CPU = textwrap.dedent("""
    import sys, torch
    sys.path.insert(0, {tests!r})
    from hemirad.transport.gl import GLContext
    GLContext.get(gpu=True)
    from test_device import refining_solve
    import hemirad
    from hemirad.transport.renderer import HemicubeRenderer
    from hemirad.scene.meshing import build_mesh

    mesh = build_mesh(hemirad.load_scene("cornell_box"))
    cpu, gpu = HemicubeRenderer(mesh, 128), HemicubeRenderer(mesh.to("cuda"), 128, device="cuda")
    for shooter in (0, mesh.num_elements // 2, mesh.num_elements - 1):
        a, b = cpu.from_element(shooter), gpu.from_element(shooter)
        assert b.device.type == "cuda" and torch.allclose(a, b.cpu(), rtol=1e-12, atol=1e-15), shooter
    for criterion in ("gradient", "partial_visibility"):
        a, b = refining_solve(criterion, "cpu", 20), refining_solve(criterion, "cuda", 20)
        ta, tb = len(a["mesh"]["triangles"]), len(b["mesh"]["triangles"])
        assert abs(ta - tb) <= 0.005 * ta, (criterion, ta, tb)
        if ta == tb:
            assert torch.allclose(a["radiosity"], b["radiosity"], rtol=1e-9, atol=1e-12), criterion
        assert torch.allclose(a["absorbed"], b["absorbed"], rtol=1e-3), criterion
    assert torch.equal(refining_solve("gradient", "cuda", 10)["radiosity"],
                       refining_solve("gradient", "cuda", 10)["radiosity"])  # deterministic
    print("renderer", GLContext.renderer_name())
""")


@pytest.mark.skipif(not CUDA, reason="needs a CUDA device (and an NVIDIA EGL driver)")
def test_the_cuda_path_gives_the_cpu_paths_form_factors_and_solutions():
    from pathlib import Path

    script = _CUDA_AGAINST_CPU.format(tests=str(Path(__file__).parent))
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "llvmpipe" not in done.stdout


@pytest.mark.skipif(CUDA, reason="this machine may have a hardware EGL device")
def test_a_gpu_context_without_a_hardware_egl_device_is_a_clear_error():
    # in a fresh process: opening EGL devices would change which context is current here
    script = textwrap.dedent("""
        from hemirad.core.errors import HemiradInputError
        from hemirad.transport.gl import GLContext
        try:
            GLContext.get(gpu=True)
        except HemiradInputError as exc:
            print(exc)
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "no EGL device renders in hardware" in done.stdout and "--device cpu" in done.stdout
