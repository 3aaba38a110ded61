"""Each refinement criterion's score on hand-made shots."""
import math

import pytest
import torch

from hemirad.adaptive.criteria import (ShotContext, gradient_score, neighbor_difference_score, partial_visibility_score,
                              receiver_score, uniform_score)
from hemirad.core.colour import luminance
from hemirad.geometry.analytic import point_to_triangles

from patches import quad, quads_mesh

ONE = torch.ones(3, dtype=torch.float64)


def context(mesh, shooter=0, **fields):
    T = mesh.num_elements
    base = dict(eye=torch.tensor([0.5, 0.5, 1.0], dtype=torch.float64),
                normal=torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64),
                form_factors=torch.zeros(T, dtype=torch.float64),
                luminance_per_form_factor=torch.ones(T, dtype=torch.float64), jacobian=None)
    base.update(fields)
    return ShotContext(mesh, shooter, **base)


@pytest.fixture
def grid():
    """A unit square in z = 0 facing up, as 4 x 4 cells (32 elements)."""
    return quads_mesh([quad([0, 0, 0], [1, 0, 0], [0, 1, 0])], [0.25])


def test_gradient_score_is_eq_7(grid):
    T = grid.num_elements
    J = torch.zeros(T, 3, dtype=torch.float64)
    J[5] = torch.tensor([2.0, 0.0, 0.0])
    scale = torch.full((T,), 3.0, dtype=torch.float64)
    score = gradient_score(context(grid, shooter=0, jacobian=J, luminance_per_form_factor=scale))
    offsets = grid.corners[0] - grid.corners[0].mean(0)
    assert float(score[5]) == pytest.approx(3.0 * 2.0 * float(offsets[:, 0].abs().max()))
    assert float(score.abs().sum() - score[5]) == 0.0


def test_receiver_score_uses_the_receivers_own_extent(grid):
    T = grid.num_elements
    J = torch.zeros(T, 3, dtype=torch.float64)
    J[:, 1] = 1.0  # the same gradient along y everywhere
    score = receiver_score(context(grid, jacobian=J))
    corners = grid.corners
    spread = (corners[..., 1] - corners[..., 1].mean(1, keepdim=True)).abs().amax(1)
    torch.testing.assert_close(score, spread)


def test_partial_visibility_scores_the_missing_part(grid):
    unoccluded = point_to_triangles(torch.tensor([0.5, 0.5, 1.0], dtype=torch.float64),
                                    torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64), grid.corners)
    F = unoccluded.clone()
    F[3] *= 0.5  # half hidden
    F[4] = 0.0  # wholly hidden: not on a shadow edge
    score = partial_visibility_score(context(grid, form_factors=F))
    assert float(score[3]) == pytest.approx(0.5 * float(unoccluded[3]))
    assert float(score[4]) == 0.0
    assert float(score.max()) == float(score[3])


def test_neighbor_difference_flags_both_sides_of_a_step(grid):
    step = (grid.centroids[:, 0] > 0.5).to(torch.float64)  # F_sj, on white receivers
    score = neighbor_difference_score(context(grid, form_factors=step,
                                              luminance_per_form_factor=luminance(ONE).expand(len(step))))
    near_step = (grid.centroids[:, 0] - 0.5).abs() < 0.25
    assert torch.allclose(score[near_step], luminance(ONE).expand(int(near_step.sum())))
    assert float(score[~near_step].abs().max()) == 0.0


def test_uniform_score_is_the_longest_edge(grid):
    score = uniform_score(context(grid))
    torch.testing.assert_close(score, torch.full_like(score, 0.25 * math.sqrt(2)))


def test_every_criterion_scores_some_rows_as_it_scores_all(grid):
    # The refiner scores only a pass's candidates; their scores must be those of the full pass.
    from hemirad.adaptive.criteria import CRITERIA

    T = grid.num_elements
    g = torch.Generator().manual_seed(5)
    ctx = context(grid, form_factors=torch.rand(T, generator=g, dtype=torch.float64) * 0.01,
                  luminance_per_form_factor=torch.rand(T, generator=g, dtype=torch.float64),
                  jacobian=torch.randn(T, 3, generator=g, dtype=torch.float64))
    rows = torch.tensor([3, 0, 17, T - 1])
    for name, criterion in CRITERIA.items():
        full = criterion.score(ctx, None)
        assert full.shape == (T,) and full.abs().sum() > 0, name
        torch.testing.assert_close(criterion.score(ctx, rows), full[rows], rtol=1e-14, atol=0, msg=name)
