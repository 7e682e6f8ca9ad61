"""Fixtures shared by the test files (helpers called as plain functions live in modules beside
this one, e.g. render_helpers.py, imported by name: pytest puts tests/ on sys.path). The Blender
tests (tests/blender, in Blender's own Python without torch) load this file too: import torch
only inside the fixtures that need it."""

import os

import pytest

# the simulator's two lanes (sim/lanes.py) sum the grid in another order than one lane: tests that compare runs
# bitwise (graphs against eager launches, threads against one after another) run on one lane, whatever the
# machine's load; tests/test_sim_lanes.py (and test_fit_lanes.py) switch the lanes on themselves
os.environ.setdefault("PHYSINTERACT_SIM_LANES", "1")
# the fit's independent forwards (simulation.sim_threads: two threads where a core sits idle) give the same
# results on one thread or two; the suite runs them on one (its CPU time does not depend on the machine's load);
# tests/test_sim_threads.py and test_fit_probes_threads.py switch two on themselves
os.environ.setdefault("PHYSINTERACT_SIM_THREADS", "1")


@pytest.fixture
def one_torch_thread():
    """Tiny tensors: torch's thread pool only adds overhead (a lot of it on a busy 2-core box).
    A module opts in with `pytestmark = pytest.mark.usefixtures("one_torch_thread")`."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
