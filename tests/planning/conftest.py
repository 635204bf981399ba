import pytest
import torch


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """These models are tiny: one intra-op thread is fastest and stays fast on a busy machine
    (OpenMP threads spinning against other processes made the suite ~2.5x slower)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
