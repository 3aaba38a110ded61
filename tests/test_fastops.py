"""The fast idioms give what the plain torch calls they replace give, bit for bit."""
import numpy as np
import torch

from hemirad.core.fastops import cross3, flatnonzero, marked_positions, row_sums, rows_touching, take_or_none


def test_row_sums_is_sum_over_the_three_columns():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(1000, 3, dtype=torch.float64, generator=g) * torch.logspace(-8, 8, 1000, dtype=torch.float64)[:, None]
    assert torch.equal(row_sums(x), x.sum(1))


def test_flatnonzero_is_torch_nonzero():
    g = torch.Generator().manual_seed(1)
    mask = torch.rand(5000, generator=g) < 0.3
    for m in (mask, mask[::3], torch.zeros(0, dtype=torch.bool), torch.zeros(7, dtype=torch.bool), mask.reshape(50, 100)[:, 4]):
        found = flatnonzero(m)
        assert found.dtype == torch.int64 and torch.equal(found, torch.nonzero(m).reshape(-1))


def test_marked_positions_and_rows_touching_are_their_torch_forms():
    g = torch.Generator().manual_seed(2)
    table = torch.rand(300, generator=g) < 0.2
    index = torch.randint(-1, 300, (4000,), generator=g)
    expected = torch.nonzero((index >= 0) & table[index.clamp(min=0)]).reshape(-1)
    assert torch.equal(marked_positions(index, table), expected)
    assert len(marked_positions(torch.full((5,), -1), table)) == 0
    ids = torch.randint(0, 50, (300,), generator=g)
    assert torch.equal(take_or_none(ids, index), torch.where(index >= 0, ids[index.clamp(min=0)], -1))
    rows = torch.randint(0, 300, (1000, 3), generator=g)
    assert torch.equal(rows_touching(rows, table), torch.nonzero(table[rows].any(dim=1)).reshape(-1))


def test_cross3_is_numpy_cross_bit_for_bit():
    rng = np.random.default_rng(0)
    for shape_a, shape_b in [((50, 3), (50, 3)), ((3,), (3,)), ((4, 1, 3), (4, 3, 3)), ((6, 3), (3,))]:
        a, b = rng.normal(size=shape_a), rng.normal(size=shape_b)
        assert np.array_equal(cross3(a, b), np.cross(a, b))
        assert cross3(a.astype(np.float32), b.astype(np.float32)).dtype == np.float32
    assert cross3([1, 0, 0], [0, 1, 0]).tolist() == [0, 0, 1]  # lists, ints: x cross y is z
