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


def test_preload_is_a_no_op_on_cuda():
    """The preload runs on the CPU only: on CUDA the same thread (with the CUDA context) measured no gain on
    the H200 and was removed (#26; docs/benchmarks/gpu.md, session 17)."""
    from physinteract_usd.sim import kernels as sk

    before = dict(sk._PRELOAD)
    sk.preload("cuda:0", "float64")
    assert sk._PRELOAD == before
