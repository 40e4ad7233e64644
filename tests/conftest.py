"""Shared pytest fixtures."""

import pytest
import torch


@pytest.fixture
def one_thread():
    """Many tiny ops: one thread avoids OpenMP spin-waits when other processes share the cores."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
