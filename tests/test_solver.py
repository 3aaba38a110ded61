"""Progressive refinement against conservation laws and closed-box solutions."""
import pytest
import torch

from hemirad.transport.solver import ProgressiveSolver, ambient_term

from patches import assert_power_balances, closed_box, random_materials


def solve_box(reflectance, emission, element_size=1.0, resolution=64, unshot_fraction=1e-5, max_shots=20000):
    mesh = closed_box(element_size=element_size)
    T = mesh.num_elements
    rho = torch.as_tensor(reflectance, dtype=torch.float64).expand(T, 3).clone()
    E = torch.as_tensor(emission, dtype=torch.float64).expand(T, 3).clone()
    solver = ProgressiveSolver(mesh, rho, E, resolution)
    try:
        state = solver.run(max_shots, unshot_fraction)
        return mesh, rho, E, state, solver.unshot_fraction
    finally:
        solver.close()


def test_energy_balance_in_a_closed_room():
    mesh = closed_box(element_size=0.25)
    rho, E = random_materials(mesh.num_elements, seed=0, span=0.8, low=0.1, glowing=4,
                              emission=(10.0, 7.0, 3.0))  # a corner of one wall glows
    solver = ProgressiveSolver(mesh, rho, E, 64)
    try:
        state = solver.run(max_shots=60, unshot_fraction=0.0)
    finally:
        solver.close()
    emitted = (E * mesh.areas[:, None]).sum(0)
    assert state.shots == 60
    # what reached each front, recovered from the radiosities independently of the solver's sums
    assert_power_balances(state, mesh.areas, rho, E, emitted, rtol=1e-6)
    assert float(state.escaped.abs().max()) < 1e-9 * float(emitted.max())  # nothing leaks out of a closed box


@pytest.mark.parametrize("rho", [0.3, 0.5, 0.8])
def test_uniformly_emitting_closed_box_converges_to_e_over_one_minus_rho(rho):
    E = torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64)
    mesh, _, _, state, unshot_fraction = solve_box(rho, E, resolution=128)
    assert unshot_fraction <= 1e-5
    expected = E / (1 - rho)
    assert torch.allclose(state.radiosity, expected.expand_as(state.radiosity), rtol=1e-2)


def test_closed_box_mean_radiosity_is_exact_on_a_finer_mesh():
    # Per element, a hemicube from a centroid is not reciprocal near corners (a few % there);
    # but power is conserved exactly, so the area-weighted mean is E / (1 - rho) to rounding.
    mesh, _, E, state, _ = solve_box(0.5, [1.0, 1.0, 1.0], element_size=0.25, unshot_fraction=1e-7)
    mean = (state.radiosity * mesh.areas[:, None]).sum(0) / mesh.areas.sum()
    torch.testing.assert_close(mean, torch.full((3,), 2.0, dtype=torch.float64), rtol=1e-6, atol=0)


def test_ambient_term_fills_in_the_unshot_energy():
    # Before any shot, the ambient of a uniformly emitting closed box already gives the answer.
    mesh = closed_box(element_size=0.5)
    T = mesh.num_elements
    rho = torch.full((T, 3), 0.6, dtype=torch.float64)
    E = torch.full((T, 3), 2.0, dtype=torch.float64)
    displayed = E + rho * ambient_term(E, rho, mesh.areas)
    torch.testing.assert_close(displayed, E / (1 - rho))


def test_solver_is_deterministic():
    runs = [solve_box(0.5, [1.0, 0.0, 0.0], element_size=0.5, max_shots=30, unshot_fraction=0)[3] for _ in range(2)]
    assert torch.equal(runs[0].radiosity, runs[1].radiosity)


def test_kept_form_factor_rows_give_the_rendered_solve_bit_for_bit():
    # A shooter that shoots again reuses its row: the same numbers as rendering every shot,
    # with one render per distinct shooter.
    mesh = closed_box(element_size=0.5)
    T = mesh.num_elements
    rho = torch.full((T, 3), 0.7, dtype=torch.float64)
    E = torch.zeros(T, 3, dtype=torch.float64)
    E[0] = 5.0
    states, renders = [], []
    for cache_bytes in (1 << 20, 0):
        solver = ProgressiveSolver(mesh, rho, E, 32, cache_bytes=cache_bytes)
        try:
            states.append(solver.run(max_shots=300, unshot_fraction=0.0))
            renders.append(solver.hemicubes_rendered)
        finally:
            solver.close()
    assert torch.equal(states[0].radiosity, states[1].radiosity) and torch.equal(states[0].unshot, states[1].unshot)
    assert renders[1] == 300 and renders[0] <= T < 300


def test_form_factor_rows_stay_within_their_budget():
    from hemirad.transport.rowcache import FormFactorRows

    rows = FormFactorRows(budget_bytes=3 * 12 * 10)  # three rows of ten elements reached
    row = torch.zeros(100, dtype=torch.float64)
    row[:10] = 0.01
    for shooter in range(5):
        rows.put(shooter, row * (shooter + 1))
    assert len(rows) == 3 and rows.nbytes <= rows.budget_bytes
    assert rows.get(0, 100) is None and torch.equal(rows.get(4, 100), row * 5)  # oldest dropped first
    rows.put(5, row)
    assert rows.get(2, 100) is None and rows.get(3, 100) is not None  # the least recently used went
    rows.clear()
    assert len(rows) == 0 and rows.get(3, 100) is None
