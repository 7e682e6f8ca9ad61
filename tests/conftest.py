"""Fixtures shared by the test files (helpers called as plain functions live in modules beside
this one, e.g. render_helpers.py, imported by name: pytest puts tests/ on sys.path)."""

import pytest
import torch


@pytest.fixture
def one_torch_thread():
    """Tiny tensors: torch's thread pool only adds overhead (a lot of it on a busy 2-core box).
    A module opts in with `pytestmark = pytest.mark.usefixtures("one_torch_thread")`."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
