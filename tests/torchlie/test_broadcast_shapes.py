"""``torchlie._batch.broadcast_shapes`` (the solvers' fast path) against ``torch.broadcast_shapes``."""

import itertools

import pytest
import torch

from torchlie._batch import broadcast_shapes

SIZES = [(), (0,), (1,), (3,), (1, 3), (2, 1), (2, 3), (0, 3), (4, 1, 3), (4, 0, 1), (5, 2, 3)]


@pytest.mark.parametrize("a,b", list(itertools.product(SIZES, SIZES)))
def test_same_result_or_same_error_as_torch(a, b):
    try:
        want = torch.broadcast_shapes(a, b)
    except RuntimeError as e:
        with pytest.raises(RuntimeError) as got:
            broadcast_shapes(torch.Size(a), b)
        assert str(got.value) == str(e)
        return
    got = broadcast_shapes(torch.Size(a), b)
    assert got == want and isinstance(got, torch.Size)


def test_three_shapes_none_and_ints():
    assert broadcast_shapes() == torch.Size([])
    assert broadcast_shapes((2, 1), (1, 4), (3, 1, 1)) == torch.Size([3, 2, 4])
    assert broadcast_shapes(3, (2, 1)) == torch.broadcast_shapes(3, (2, 1))  # ints go to torch
    with pytest.raises(ValueError, match="negative"):
        broadcast_shapes((-1,), (2,))  # a negative size is torch's error, not a shape
