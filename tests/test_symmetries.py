"""D's repair under the square's symmetries: exact inverses, averaging, range checks."""

import pytest
import torch

from wgs.config import check_choices
from wgs.errors import InputError
from wgs.models.repair import SYMMETRIES, _apply_symmetry, symmetrized
from wgs.stages.repair.settings import RepairConfig


def test_every_symmetry_is_undone_exactly_on_a_non_square_image():
    x = torch.rand(2, 3, 5, 8, dtype=torch.float64)
    outs = set()
    for s in SYMMETRIES:
        y = _apply_symmetry(x, s)
        assert y.shape == ((2, 3, 8, 5) if s[0] else x.shape)
        assert torch.equal(_apply_symmetry(y, s, inverse=True), x)
        outs.add(y.contiguous().numpy().tobytes())
    assert len(outs) == len(SYMMETRIES)  # eight different images


def test_an_equivariant_repair_is_unchanged():
    def fn(x):
        return 2 * x - 0.5  # pointwise: equivariant to every symmetry

    x = torch.rand(1, 3, 6, 6, dtype=torch.float64)
    for n in (1, 3, 8):
        torch.testing.assert_close(symmetrized(fn, n, first=2)(x), fn(x), rtol=0, atol=1e-12)


def test_a_non_equivariant_repair_is_averaged_over_its_symmetries():
    def fn(x):
        return x.cumsum(-1)  # depends on the direction of the columns

    x = torch.rand(1, 3, 4, 6, dtype=torch.float64)
    assert symmetrized(fn, 1) is fn
    both = symmetrized(fn, 2)(x)  # identity and the column flip
    torch.testing.assert_close(both, (x.cumsum(-1) + x.flip(-1).cumsum(-1).flip(-1)) / 2)
    # `first` picks where the cycle starts: member k of an ensemble gets its own
    torch.testing.assert_close(symmetrized(fn, 1, first=1)(x), x.flip(-1).cumsum(-1).flip(-1))
    torch.testing.assert_close(symmetrized(fn, 1, first=8)(x), fn(x))  # cyclic


@pytest.mark.parametrize("n", [0, 9])
def test_symmetries_out_of_range_are_refused(n):
    with pytest.raises(ValueError, match="symmetries"):
        symmetrized(lambda x: x, n)
    with pytest.raises(InputError, match="symmetries"):
        check_choices(RepairConfig(symmetries=n))
