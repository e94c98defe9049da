"""Tests of the small tensor helpers (psmini._tensor) against direct computations."""

import pytest
import torch

from psmini._tensor import box_sum, masked_mean, vector_length
from psmini.errors import InputError


def _windowed_sums(x: torch.Tensor, size: int) -> torch.Tensor:
    """Each pixel's window summed offset by offset over a zero-padded copy: the definition, written out."""
    half = size // 2
    padded = torch.nn.functional.pad(x, (half, half, half, half))
    height, width = x.shape[-2:]
    return sum(padded[..., i : i + height, j : j + width] for i in range(size) for j in range(size))


class TestBoxSum:
    @pytest.mark.parametrize("size", [1, 3, 9])
    def test_equals_the_windows_sums(self, size):
        x = torch.randn(2, 3, 11, 14, dtype=torch.float64)
        torch.testing.assert_close(box_sum(x, size), _windowed_sums(x, size))

    def test_leading_dimensions_any(self):
        x = torch.randn(5, 7, dtype=torch.float64)
        torch.testing.assert_close(box_sum(x, 3), _windowed_sums(x, 3))

    def test_gradcheck(self):
        x = torch.randn(1, 1, 6, 5, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(lambda t: box_sum(t, 3), (x,))

    @pytest.mark.parametrize("size", [0, 4, -3, 2.0, True])
    def test_refuses_a_window_without_a_centre(self, size):
        with pytest.raises(InputError, match="positive odd"):
            box_sum(torch.zeros(1, 1, 4, 4), size)


class TestVectorLength:
    def test_equals_the_norm(self):
        x = torch.randn(2, 8, 3, 5, 4, dtype=torch.float64)
        torch.testing.assert_close(vector_length(x, dim=2), torch.linalg.vector_norm(x, dim=2, keepdim=True))

    def test_zero_vector_has_a_finite_gradient(self):
        x = torch.zeros(1, 3, dtype=torch.float64, requires_grad=True)
        vector_length(x, dim=1).sum().backward()
        assert bool(torch.isfinite(x.grad).all())


class TestMaskedMean:
    def test_equals_numpy_per_sample_and_per_channel(self):
        x = torch.randn(2, 3, 5, 4, dtype=torch.float64)
        region = torch.rand(2, 1, 5, 4, generator=torch.Generator().manual_seed(0)) > 0.4
        values, keep = x.numpy(), region.expand_as(x).numpy()
        for b in range(2):
            assert float(masked_mean(x, region)[b]) == pytest.approx(values[b][keep[b]].mean())
            for c in range(3):
                assert float(masked_mean(x, region, dim=(2, 3))[b, c]) == pytest.approx(values[b, c][keep[b, c]].mean())

    def test_weights_and_an_empty_region(self):
        x = torch.tensor([[[[1.0, 3.0]]]])
        assert float(masked_mean(x, torch.tensor([[[[1.0, 3.0]]]]))) == pytest.approx(2.5)
        assert float(masked_mean(x, torch.zeros_like(x, dtype=torch.bool))) == 0.0

    def test_gradcheck(self):
        x = torch.randn(1, 2, 3, 3, dtype=torch.float64, requires_grad=True)
        region = torch.rand(1, 1, 3, 3, generator=torch.Generator().manual_seed(1)) > 0.3
        assert torch.autograd.gradcheck(lambda t: masked_mean(t, region, dim=(2, 3)), (x,))
