"""Shared fixtures for the kernel tests."""
import pytest
import torch


@pytest.fixture(autouse=True)
def one_thread():
    """Tiny tensors: with 2 threads on a busy 2-core machine, OpenMP's hand-offs made these
    tests up to 8x slower (24 s vs 3 s for the fit); the tensors are too small to need two."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)
