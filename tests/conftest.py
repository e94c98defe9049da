"""Fixtures shared by the test suite: devices, dtypes, reference data, and a kornia-style base tester."""

from __future__ import annotations

# psmini before torch: it asks OpenMP to let idle threads sleep (psmini.threads), which keeps the suite from
# stalling when other processes share the cores (the split keeps the import sorter from moving it after torch)
import psmini  # noqa: F401

# isort: split
import os
from pathlib import Path

import pytest
import torch

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

# Under pytest-xdist (``-n auto``) each worker takes its share of the cores: two workers with two threads each on a
# 2-core machine wait on each other at every parallel region (psmini.threads)
if "PYTEST_XDIST_WORKER_COUNT" in os.environ and "OMP_NUM_THREADS" not in os.environ:
    psmini.set_threads(max(1, (os.cpu_count() or 1) // int(os.environ["PYTEST_XDIST_WORKER_COUNT"])))

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    return torch.device(request.param)


@pytest.fixture(params=[torch.float32, torch.float64], ids=["float32", "float64"])
def dtype(request) -> torch.dtype:
    return request.param


@pytest.fixture
def cuda_device() -> torch.device:
    if not torch.cuda.is_available():
        pytest.skip("CUDA is not available on this machine")
    return torch.device("cuda")


def shared_data(*parts: str) -> Path:
    """Path under ../shared/data, or skip the test with the reason when it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"reference data {path} is absent (it lives beside the repository in ../shared/data)")
    return path


class BaseTester:
    """Tolerances by dtype and a float64 gradcheck, in kornia's manner."""

    @staticmethod
    def tolerance(dtype: torch.dtype) -> tuple[float, float]:
        return (1e-4, 1e-4) if dtype == torch.float32 else (1e-9, 1e-9)

    def assert_close(self, actual, expected, rtol: float | None = None, atol: float | None = None) -> None:
        default_rtol, default_atol = self.tolerance(actual.dtype)
        torch.testing.assert_close(
            actual, expected, rtol=default_rtol if rtol is None else rtol, atol=default_atol if atol is None else atol
        )

    @staticmethod
    def gradcheck(func, inputs, **kwargs) -> None:
        inputs = tuple(inputs) if isinstance(inputs, (tuple, list)) else (inputs,)
        assert torch.autograd.gradcheck(func, inputs, **kwargs)
