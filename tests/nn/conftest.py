import pytest
import torch


@pytest.fixture(autouse=True, scope="module")
def float64_default():
    """The layers' checks run in float64; restored after, so other modules keep float32."""
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(old)
