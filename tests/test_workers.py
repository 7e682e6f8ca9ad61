"""`workers.fork_map`: independent CPU work in forked processes (#22, #26). The results are the sequential map's, in
order; the work really leaves the parent; an item's exception reaches the caller as itself; an item whose worker dies
is computed in the parent; the process count follows PHYSINTERACT_WORKERS, and CUDA never forks."""

import os
import signal
import sys

import pytest

from physinteract_usd import workers
from physinteract_usd.errors import InputError

linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="fork_map forks on Linux only")


@linux
def test_the_results_are_the_maps_in_order_and_computed_in_other_processes():
    parent = os.getpid()
    got = workers.fork_map(lambda x: (x * x, os.getpid()), range(7), workers=3)
    assert [v for v, _ in got] == [x * x for x in range(7)]
    pids = {p for _, p in got}
    assert parent not in pids and len(pids) == 7          # one child per item, none of them the parent


@linux
def test_the_parents_state_at_the_call_is_what_each_child_starts_from():
    import numpy as np

    big = np.arange(200_000, dtype=np.float64)            # shared copy-on-write, not pickled over
    state = {"calls": 0}

    def f(k):
        state["calls"] += 1                                # a child's change stays in the child
        return float(big[k::7].sum()), state["calls"]

    got = workers.fork_map(f, range(7), workers=2)
    assert [s for s, _ in got] == [float(big[k::7].sum()) for k in range(7)]
    assert all(c == 1 for _, c in got) and state["calls"] == 0


@linux
def test_an_items_exception_is_raised_as_itself_the_first_in_order():
    def f(x):
        if x >= 2:
            raise ValueError(f"item {x} is bad")
        return x

    with pytest.raises(ValueError, match="item 2 is bad"):
        workers.fork_map(f, range(5), workers=2)


@linux
def test_an_unpicklable_result_is_an_error_with_the_workers_traceback():
    with pytest.raises(workers.WorkerError, match="independent run failed"):
        workers.fork_map(lambda x: (lambda: x), range(2), workers=2)


@linux
def test_an_item_whose_worker_dies_is_computed_in_the_parent():
    parent = os.getpid()

    def f(x):
        if x == 1 and os.getpid() != parent:
            os.kill(os.getpid(), signal.SIGKILL)            # as the kernel's OOM killer would
        return x + 10, os.getpid()

    got = workers.fork_map(f, range(3), workers=2)
    assert [v for v, _ in got] == [10, 11, 12]
    assert got[1][1] == parent and got[0][1] != parent


def test_one_process_when_asked_or_on_cuda(monkeypatch):
    parent = os.getpid()
    monkeypatch.setenv(workers.ENV, "1")
    assert [p for p in workers.fork_map(lambda x: os.getpid(), range(3))] == [parent] * 3
    monkeypatch.delenv(workers.ENV)
    assert workers.fork_map(lambda x: os.getpid(), range(3), device="cuda:0", workers=3) == [parent] * 3
    assert workers.workers_for(1) == 1
    monkeypatch.setenv(workers.ENV, "4")
    assert workers.workers_for(9) == 4 and workers.workers_for(2) == 2
    # `forks` says beforehand what fork_map will do (diagnose shows its own progress bar when it runs in one process)
    assert workers.forks(3) is sys.platform.startswith("linux") and not workers.forks(1) and not workers.forks(3, "cuda")
    monkeypatch.setenv(workers.ENV, "1")
    assert not workers.forks(3)


@pytest.mark.parametrize("bad", ["0", "two", "-3"])
def test_a_bad_worker_count_is_one_line_naming_the_setting(monkeypatch, bad):
    monkeypatch.setenv(workers.ENV, bad)
    with pytest.raises(InputError, match="PHYSINTERACT_WORKERS") as e:
        workers.workers_for(3)
    assert "\n" not in str(e.value)


@linux
def test_children_of_a_parent_whose_torch_ran_threads_still_run_torch():
    """A parent that ran a parallel torch op on 2 threads leaves its children libgomp's pool without its threads:
    their next parallel op waited forever (the walkthrough's diagnose hung so) until each child took one thread."""
    import torch

    before = torch.get_num_threads()
    old = signal.signal(signal.SIGALRM, lambda *a: (_ for _ in ()).throw(TimeoutError("a worker hung")))
    try:
        torch.set_num_threads(2)
        x = torch.rand(2_000_000, dtype=torch.float64)
        idx = torch.randint(0, len(x), (2_000_000,))
        want = float(x[idx].sum())                         # the pool made here, in the parent
        signal.alarm(60)
        got = workers.fork_map(lambda k: float(x[idx].sum()), range(2), workers=2)
        assert got == pytest.approx([want, want], rel=1e-12)      # one thread there: another summation order
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
        torch.set_num_threads(before)


@linux
def test_a_worker_forks_no_workers_of_its_own():
    def inner(k):
        return workers.fork_map(lambda j: os.getpid(), range(3), workers=3)

    for kid, pids in zip(range(2), workers.fork_map(lambda k: (os.getpid(), inner(k)), range(2), workers=2)):
        me, theirs = pids
        assert theirs == [me] * 3


@linux
def test_the_workers_end_with_their_parent(tmp_path):
    """A parent killed outright (SIGKILL: no cleanup runs) takes its workers with it: none computes on, orphaned."""
    import subprocess
    import textwrap
    import time

    script = tmp_path / "parent.py"
    script.write_text(textwrap.dedent(f"""
        import os, time
        from physinteract_usd import workers
        def f(k):
            open(os.path.join({str(tmp_path)!r}, f"w{{os.getpid()}}"), "w").close()
            time.sleep(60)
        workers.fork_map(f, range(2), workers=2)
    """))
    p = subprocess.Popen([sys.executable, str(script)])
    deadline = time.time() + 30
    while len(list(tmp_path.glob("w*"))) < 2 and time.time() < deadline:
        time.sleep(0.05)
    kids = [int(q.name[1:]) for q in tmp_path.glob("w*")]
    assert len(kids) == 2
    p.kill()
    p.wait()

    def alive(pid):
        try:
            return open(f"/proc/{pid}/stat").read().split()[2] != "Z"    # a zombie has ended (init reaps it)
        except FileNotFoundError:
            return False

    deadline = time.time() + 5
    while any(alive(k) for k in kids) and time.time() < deadline:
        time.sleep(0.05)
    assert not any(alive(k) for k in kids)
