"""Stopping real fits (tests/fit_scene.py's tiny bar): SIGTERM and SIGINT sent to a `fit` process
write its best iterate within 5 s, as a version that never replaces a complete one; a fit killed
with SIGKILL goes on from its checkpoint with `--resume`; a stop that lands after the iterations (in
the confidence estimate) or before the first one loses nothing that was there."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from pxr import Sdf

import fit_scene as fs
import physinteract_usd  # noqa: F401  (registers the schemas)
import physinteract_usd.fit.optimize as optimize
from physinteract_usd import api, stopping
from physinteract_usd.usd.layout import LayerPaths
from physinteract_usd.usd.stage import read_stage
from version_helpers import tree_md5

QUIET = dict(progress=False, log=lambda *a: None)
SETTINGS = dict(fs.SMOKE_SETTINGS, confidence_probes=1)
STOP_BOUND_S = 5.0


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return fs.build(tmp_path_factory.mktemp("stop") / "base")


@pytest.fixture
def stage(scene, tmp_path):
    return fs.copy_scene(scene["root"], tmp_path / "s")


def _start_fit(stage, *extra):
    return subprocess.Popen([sys.executable, "-m", "physinteract_usd", "fit", str(stage), "--contact-from",
                             str(stage.parent / "gt"), "--checkpoint-every", "1", "--patience", "0", *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for_iterations(proc, stage, timeout=240.0):
    """Until the fit has checkpointed (it is iterating); then a little more."""
    ck = LayerPaths.of(stage).checkpoint
    t0 = time.time()
    while not ck.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.time() - t0 < timeout, "the fit never reached its first checkpoint"
        time.sleep(0.05)
    time.sleep(0.5)


def _stop(proc, sig):
    t = time.time()
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=60)
    return time.time() - t, proc.returncode, out, err


def _fit_layer_e(stage):
    layer = Sdf.Layer.OpenAsAnonymous(str(LayerPaths.of(stage).fit))
    return np.asarray(layer.GetAttributeAtPath(
        "/World/Object/SimParticles.primvars:physinteract:youngsModulus").default, np.float64)


def test_sigterm_then_sigint_keep_the_best_iterate_and_never_replace_a_complete_fit(stage):
    # 1. SIGTERM (what `timeout`, schedulers and Ray send) on a first fit: its best iterate is
    #    written as an interrupted version, shown since there is no other
    p = _start_fit(stage, "--iterations", "400")
    _wait_for_iterations(p, stage)
    took, code, out, err = _stop(p, signal.SIGTERM)
    assert code == 130, err
    assert took < STOP_BOUND_S, f"SIGTERM: written and exited after {took:.1f} s"
    assert "stopped by SIGTERM" in out and "confidence not estimated" in out
    sd = read_stage(stage)
    (v1,) = sd.reports
    assert v1["status"] == "interrupted" and not v1["confidence_estimated"] and v1["current"]
    assert 0 < len(v1["loss_history"]) < 400
    assert v1["final_loss"] <= min(v1["loss_history"]) * 1.0001   # the best iterate, not the last
    assert np.all(sd.confidence == 0)                              # not estimated: claims nothing
    assert not LayerPaths.of(stage).checkpoint.exists()            # the version supersedes it

    # 2. a complete fit replaces an interrupted one
    out2 = api.fit(stage, iterations=3, contact_from=stage.parent / "gt", settings_overrides=SETTINGS, **QUIET)
    assert out2.version == 2 and out2.current == 2
    e2 = _fit_layer_e(stage)
    v2_snapshot = tree_md5(LayerPaths.of(stage).versions)["v2.usdc"]

    # 3. SIGINT on the next fit: kept as v3, but v2 (complete) stays current, untouched
    p = _start_fit(stage, "--iterations", "400", "--no-keep-best")
    _wait_for_iterations(p, stage)
    took, code, out, err = _stop(p, signal.SIGINT)
    assert code == 130, err
    assert took < STOP_BOUND_S, f"SIGINT: written and exited after {took:.1f} s"
    assert "v2 stays current" in out and "interrupted" in out
    sd = read_stage(stage)
    assert [(r["version"], r["status"], r["current"]) for r in sd.reports] == [
        (1, "interrupted", False), (2, "complete", True), (3, "interrupted", False)]
    np.testing.assert_array_equal(_fit_layer_e(stage), e2)
    assert tree_md5(LayerPaths.of(stage).versions)["v2.usdc"] == v2_snapshot


def kill_after_checkpoint(p, stage, timeout: float = 240.0):
    """SIGKILL the fit `p` as soon as its checkpoint holds a best iterate (iteration >= 2); returns the checkpoint's
    path. On an idle VM a tiny fit's 40 iterations take under 1.5 s, so a kill at a fixed delay after the first
    checkpoint landed after the loop."""
    from physinteract_usd.app.fit_checkpoint import load_checkpoint

    ck = LayerPaths.of(stage).checkpoint
    t0 = time.time()
    while True:
        c = load_checkpoint(ck) if ck.exists() else None
        if c is not None and c["loss"] is not None and int(c["iteration"]) >= 2:
            break
        assert p.poll() is None, p.communicate()
        assert time.time() - t0 < timeout, "the fit never checkpointed a best iterate"
        time.sleep(0.01)
    p.kill()
    p.communicate(timeout=60)
    return ck


def test_a_killed_fit_resumes_from_its_checkpoint(stage):
    from physinteract_usd.app.fit_checkpoint import load_checkpoint

    ck = kill_after_checkpoint(_start_fit(stage, "--iterations", "40"), stage)
    assert ck.exists() and read_stage(stage).reports == []        # nothing written but the checkpoint

    saved = load_checkpoint(ck)
    done = int(saved["iteration"])
    assert 0 < done < 40 and saved["budget"] == 40
    logs = []
    out = api.fit(stage, iterations=None, contact_from=stage.parent / "gt", resume=True, progress=False,
                  log=logs.append, settings_overrides=SETTINGS)
    assert any("resuming from the checkpoint" in m and f"iteration {done} of 40" in m for m in logs), logs
    assert not any("uniform E" in m for m in logs)                 # no fresh start
    r = out.result
    assert len(r.loss_history) == 40                               # the checkpoint's iterations + the rest
    assert r.loss_history[done] <= saved["loss"] * 1.05            # it goes on from where it was
    sd = read_stage(stage)
    (v1,) = sd.reports
    assert v1["status"] == "complete" and v1["resumed_from"] == "checkpoint" and v1["current"]
    assert not ck.exists()


def test_a_stop_during_the_confidence_estimate_still_writes_the_fit(stage, monkeypatch):
    """The optimiser's loop is over; the stop lands in the confidence estimate's backward pass: the
    best iterate is written at once (complete, confidence not estimated)."""
    real = optimize.confidence

    def stopped_confidence(*a, **kw):
        stopping.request("SIGTERM")
        return real(*a, **kw)

    monkeypatch.setattr(optimize, "confidence", stopped_confidence)
    out = api.fit(stage, iterations=4, contact_from=stage.parent / "gt", settings_overrides=SETTINGS, **QUIET)
    assert out.stopped_by == "SIGTERM" and not out.confidence_estimated and not out.result.interrupted
    (v1,) = read_stage(stage).reports
    assert v1["status"] == "complete" and not v1["confidence_estimated"] and len(v1["loss_history"]) == 4


def test_a_stop_before_the_first_iteration_writes_nothing(stage, monkeypatch):
    before = tree_md5(stage.parent)
    real = optimize.golden_uniform_search

    def stopped_search(*a, **kw):
        stopping.request("SIGINT")
        return real(*a, **kw)

    monkeypatch.setattr(optimize, "golden_uniform_search", stopped_search)
    with pytest.raises(KeyboardInterrupt):
        api.fit(stage, iterations=4, contact_from=stage.parent / "gt", settings_overrides=SETTINGS, **QUIET)
    assert tree_md5(stage.parent) == before
