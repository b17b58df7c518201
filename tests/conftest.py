import pytest
import torch

from ngp_warp import _wp


def pytest_collection_modifyitems(config, items):
    """Skip tests marked ``cuda`` when no CUDA device is usable by both torch and Warp."""
    if _wp.cuda_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA GPU usable by torch and Warp")
    for item in items:
        if "cuda" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
