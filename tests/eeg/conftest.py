"""Fixtures shared by the EEG tests."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture
def one_torch_thread():
    """One intra-op thread, as the CLI and the services run training (the test process's
    setting, restored after): OpenMP threads spin, so two threads on a loaded 2-core
    machine train several times slower than one."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
