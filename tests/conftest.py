import os

import pytest
import torch

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")


@pytest.fixture(autouse=True, scope="session")
def _single_torch_thread():
    """The stages run many tiny tensor ops (filters, small solves); with several threads each becomes a
    barrier wait and a loaded 2-core machine runs them ~10x slower. The tracker CLIs default to one
    thread for the same reason, so the tests run as users do."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
