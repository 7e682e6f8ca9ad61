"""The simulator's Warp modules: split by who launches them, and compiled ahead on a second thread
by `sim.kernels.preload` (what a fit starts before its extraction, #26; docs/benchmarks/cpu.md)."""

import subprocess
import sys
import textwrap

# a fresh process: in this one, earlier tests may have built or loaded the kernels already
CHILD = textwrap.dedent("""
    import threading
    import warp as wp
    from physinteract_usd.devices import quiet_warp_init
    from physinteract_usd.sim import kernels as sk
    quiet_warp_init("cpu")
    dev = wp.get_device("cpu")
    sk.preload("cuda:0", "float64")                  # a GPU's modules differ: nothing started
    assert "float64" not in sk._PRELOAD and "float64" not in sk._CACHE
    sk.preload("cpu", "float64")
    t = sk._PRELOAD["float64"]
    assert t.name.startswith("physinteract-preload") and t is not threading.current_thread()
    K = sk.get_kernels("float64")                    # waits for the thread
    assert not t.is_alive() and "float64" not in sk._PRELOAD
    loaded = lambda name: any(key[0] == dev.context for key in wp.get_module(name).execs)
    m = K.modules
    print("LOADED", loaded(m.core), loaded(m.adj), loaded(m.rate), loaded(m.cuda), loaded(m.test))
    # the kernels sit where the split says (a launch of one compiles only its module)
    assert K.p2g_scatter.module.name == m.core and K.g2p_update.module.name == m.core
    assert K.p2g_scatter_adj.module.name == m.adj and K.g2p_gather_adj.module.name == m.adj
    assert K.p2g_fused.module.name == m.cuda and K.grid_update_box.module.name == m.cuda
    assert K.p2g_scatter_old.module.name == m.rate and K.eval_matfuncs.module.name == m.test
    assert not wp.get_module(m.adj).options["enable_backward"]
    sk.preload("cpu", "float64")                     # already built: a no-op
    assert "float64" not in sk._PRELOAD
    # what setup.sh runs after an install: the fit's modules, the renderer's too, all loaded
    from physinteract_usd.simulation import warm_kernels
    names = warm_kernels("cpu", "float64")
    assert names[:2] == [m.core, m.adj] and names[2].startswith("physinteract_render"), names
    assert all(loaded(n) for n in names) and not loaded(m.rate)
""")


def test_preload_compiles_the_substep_and_adjoint_modules_only():
    p = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    line = [ln for ln in p.stdout.splitlines() if ln.startswith("LOADED")]
    # the substep's and the hand-written adjoints' modules loaded; rate, CUDA and test modules not
    assert line == ["LOADED True True False False False"], p.stdout[-2000:]


CUDA_CHILD = textwrap.dedent("""
    import os, threading
    os.environ["PHYSINTERACT_CUDA_PRELOAD"] = "1"
    import warp as wp
    from physinteract_usd.devices import quiet_warp_init
    from physinteract_usd.sim import kernels as sk
    assert sk.CUDA_PRELOAD
    quiet_warp_init("cpu")
    ran = []
    sk.preload("cuda:0", "float64", also=["physinteract_no_such_module"], before=lambda: ran.append(1))
    t = sk._PRELOAD["float64"]                       # opted in: a thread even for a GPU's modules
    K = sk.get_kernels("float64")                    # waits for it; no GPU here: the loads fail on the thread
    assert not t.is_alive() and ran == [1] and "float64" not in sk._PRELOAD
    # the frame graphs' module the thread names is the one their kernels live in
    from physinteract_usd.sim.frame_graphs import get_frame_kernels
    G = get_frame_kernels("float64")
    names = {k.module.name for k in vars(G).values()}
    print("FRAME", sorted(names))
    sk.preload("cuda:0", "float64")                  # built: a no-op
    assert "float64" not in sk._PRELOAD
""")


def test_cuda_preload_is_opt_in_and_its_failures_stay_on_its_thread():
    p = subprocess.run([sys.executable, "-c", CUDA_CHILD], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    assert "FRAME ['physinteract_framegraph_float64']" in p.stdout, p.stdout[-2000:]


def test_cuda_context_warm_up_is_opt_in(monkeypatch):
    from physinteract_usd.devices import warm_cuda_context

    monkeypatch.delenv("PHYSINTERACT_CUDA_PRELOAD", raising=False)
    assert warm_cuda_context("cuda") is None and warm_cuda_context("cpu") is None
    monkeypatch.setenv("PHYSINTERACT_CUDA_PRELOAD", "1")
    assert warm_cuda_context("cpu") is None
    t = warm_cuda_context("cuda:0")          # opted in: a thread (on a machine without CUDA its failure stays there)
    assert t is not None and t.name == "physinteract-cuda-context"
    t.join(60)
    assert not t.is_alive()
