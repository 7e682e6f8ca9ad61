"""The batch's core without the physics: manifest parsing and its one-line errors, the step keys
(what a changed setting or file re-runs), the process pool's handling of failures, dying workers
and SIGTERM (with stand-in items that sleep, raise or kill their worker), the summary table, and
`--ray` without Ray installed."""

from __future__ import annotations

import csv
import json
import os
import signal
import sys
import threading
import time

import pytest

from physinteract_usd.batch.keys import STEPS, first_stale_step, fingerprint, step_keys
from physinteract_usd.batch.manifest import read_manifest
from physinteract_usd.batch.runner import Events, run_pool
from physinteract_usd.batch.summary import sparkline, write_csv, write_html
from physinteract_usd.errors import InputError


# ------------------------------------------------------------------------------ stand-in items (run in workers)
def fake_item(p):
    """What `app.batch.run_item` returns, without the physics: `p["do"]` says what happens."""
    do = p["do"]
    if do == "raise":
        raise RuntimeError("boom\nsecond line")
    if do == "die":
        os._exit(7)
    if do.startswith("die-once:"):   # dies on its first attempt only (a marker file remembers)
        marker = do.split(":", 1)[1]
        if not os.path.exists(marker):
            open(marker, "w").close()
            os._exit(9)
    if p.get("mark"):
        open(p["mark"], "w").close()
    try:
        time.sleep(float(p.get("sleep", 0.0)))
    except KeyboardInterrupt:
        return {"status": "interrupted", "pid": os.getpid()}
    return {"status": "done", "pid": os.getpid()}


class Rec(Events):
    def __init__(self):
        self.log = []

    def started(self, name):
        self.log.append(("started", name))

    def finished(self, name, record):
        self.log.append(("finished", name, record["status"]))

    def failed(self, name, error):
        self.log.append(("failed", name, error))

    def interrupted(self, name):
        self.log.append(("interrupted", name))

    def ends(self):
        return {e[1]: e[2:] for e in self.log if e[0] != "started"}


# ------------------------------------------------------------------------------ manifest
def test_manifest_csv_and_json(tmp_path):
    (tmp_path / "caps" / "a").mkdir(parents=True)
    m = tmp_path / "m.csv"
    m.write_text("# captures\nsource,name,iterations,effects,release_frame,support_pixel,fit_settings\n"
                 "caps/a,,5,damping;ground,never,\"1,2,3;4,5,6\",search_evals=2;levels=[1]\n"
                 "stages/x.usda,xx,,,,,\n")
    items = read_manifest(m)
    assert [i.name for i in items] == ["a", "xx"]
    a, x = items
    assert a.kind == "capture" and a.source == (tmp_path / "caps" / "a")
    assert a.options == {"iterations": 5, "effects": ["damping", "ground"], "release_frame": "never",
                         "support_pixel": ["1,2,3", "4,5,6"], "fit_settings": {"search_evals": 2, "levels": [1]}}
    assert x.kind == "stage" and x.options == {}
    j = tmp_path / "m.json"
    j.write_text(json.dumps({"defaults": {"iterations": 3, "device": "cpu"},
                             "items": ["caps/a", {"source": "caps/b", "iterations": 7, "effects": ["damping"]}]}))
    ja, jb = read_manifest(j)
    assert ja.options == {"iterations": 3, "device": "cpu"}
    assert jb.options == {"iterations": 7, "device": "cpu", "effects": ["damping"]}


@pytest.mark.parametrize("text, needle", [
    ("source,iteratons\na,3\n", "unknown key 'iteratons'"),
    ("source,iterations\na,0\n", "row 1, 'iterations': must be >= 1"),
    ("source,iterations\na,2.5\n", "row 1, 'iterations': must be a whole number"),
    ("source,effects\na,dampng\n", "unknown effect 'dampng'"),
    ("source,name\na,x\nb,x\n", "row 2: name 'x' is also row 1's"),
    ("source,device\na,tpu\n", "must be cpu or cuda"),
    ("name\nx\n", "no 'source' column"),
    ("source,youngs_range\na,5;1\n", "expected MIN,MAX"),
    ("source,name\na,bad/name\n", "'name'"),
])
def test_manifest_errors_name_the_row_and_column(tmp_path, text, needle):
    m = tmp_path / "m.csv"
    m.write_text(text)
    with pytest.raises(InputError) as e:
        read_manifest(m)
    assert str(m) in e.value.oneline() and needle in e.value.oneline(), e.value.oneline()


def test_manifest_file_errors(tmp_path):
    with pytest.raises(InputError, match="manifest not found"):
        read_manifest(tmp_path / "nope.csv")
    (tmp_path / "m.yaml").write_text("x")
    with pytest.raises(InputError, match="must be .csv or .json"):
        read_manifest(tmp_path / "m.yaml")
    (tmp_path / "m.json").write_text("[{")
    with pytest.raises(InputError, match="not valid JSON"):
        read_manifest(tmp_path / "m.json")
    (tmp_path / "e.csv").write_text("source\n")
    with pytest.raises(InputError, match="lists no items"):
        read_manifest(tmp_path / "e.csv")


def test_hint_errors_are_the_manifests(tmp_path):
    """A malformed hint is refused before anything runs, naming the manifest's row and the flag."""
    from physinteract_usd.app.batch import load_manifest

    m = tmp_path / "m.csv"
    m.write_text("source,hint_pixel\na,1;2\n")
    with pytest.raises(InputError) as e:
        load_manifest(m)
    assert str(m) in e.value.oneline() and "row 1" in e.value.oneline() and "--hint-pixel" in e.value.oneline()
    m.write_text("source,fit_settings\na,serch_evals=2\n")
    with pytest.raises(InputError, match="unknown setting 'serch_evals'"):
        load_manifest(m)


# ------------------------------------------------------------------------------ keys
def test_step_keys_rerun_what_changed(tmp_path):
    cap = tmp_path / "cap"
    (cap / "frames").mkdir(parents=True)
    (cap / "gt").mkdir()
    (cap / "frames" / "000000.png").write_bytes(b"x")
    (cap / "gt" / "truth.npy").write_bytes(b"y")
    s = {"iterations": 5, "grid": 12}
    fp = fingerprint(cap, "capture")
    assert list(fp) == ["frames/000000.png"]             # gt/ is never read by a step
    k = step_keys(s, fp)
    assert first_stale_step(k, step_keys(dict(s), fingerprint(cap, "capture"))) is None
    assert first_stale_step(k, step_keys({**s, "iterations": 6}, fp)) == "fit"
    assert first_stale_step(k, step_keys({**s, "grasp_frame": 2}, fp)) == "extract"
    assert first_stale_step(k, step_keys({**s, "grid": 16}, fp)) == "init"
    assert first_stale_step(k, step_keys({**s, "diagnose_available": True}, fp)) == "diagnose"
    assert first_stale_step(k, step_keys({**s, "sim_ready": True}, fp)) == "export"
    (cap / "gt" / "truth.npy").write_bytes(b"yy")
    assert first_stale_step(k, step_keys(s, fingerprint(cap, "capture"))) is None
    (cap / "frames" / "000000.png").write_bytes(b"xx")   # a changed input re-runs everything
    assert first_stale_step(k, step_keys(s, fingerprint(cap, "capture"))) == "init"
    assert first_stale_step({}, k) == "init" and set(k) == set(STEPS)


# ------------------------------------------------------------------------------ the pool
def test_a_stop_before_the_item_starts_keeps_it_from_starting():
    """A SIGTERM that reaches a worker before its item runs (while it starts up) is not lost."""
    import physinteract_usd.batch.runner as runner

    runner._on_sigterm(signal.SIGTERM, None)
    try:
        with pytest.raises(KeyboardInterrupt):
            runner._run_task(fake_item, {"do": "ok"})
    finally:
        runner._STOP_SEEN = False


def test_pool_failures_do_not_stop_the_rest(tmp_path):
    ev = Rec()
    tasks = [("ok1", {"do": "ok"}), ("raises", {"do": "raise"}), ("dies", {"do": "die"}),
             ("once", {"do": f"die-once:{tmp_path / 'm'}"}), ("ok2", {"do": "ok"})]
    left = run_pool(tasks, fake_item, workers=2, events=ev, retries=1)
    ends = ev.ends()
    assert left == [] and set(ends) == {n for n, _ in tasks}
    assert ends["ok1"] == ("done",) and ends["ok2"] == ("done",)
    assert ends["raises"] == ("RuntimeError: boom",)
    assert ends["once"] == ("done",)                                  # retried after its worker died
    assert "worker process died" in ends["dies"][0] and "tried 2 times alone" in ends["dies"][0]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_pool_stops_on_a_signal(tmp_path, sig):
    """The driver's first SIGTERM or SIGINT: running items are asked to stop (they come back
    interrupted), the ones not started stay to do."""
    ev = Rec()
    tasks = [(f"s{i}", {"do": "ok", "sleep": 60.0, "mark": str(tmp_path / f"s{i}")}) for i in range(4)]

    def stop_when_running():   # both workers inside their items (a busy box imports slowly)
        deadline = time.time() + 50
        while time.time() < deadline and not all((tmp_path / f"s{i}").exists() for i in range(2)):
            time.sleep(0.1)
        os.kill(os.getpid(), sig)

    threading.Thread(target=stop_when_running, daemon=True).start()
    t0 = time.perf_counter()
    left = run_pool(tasks, fake_item, workers=2, events=ev)
    took = time.perf_counter() - t0
    ends = ev.ends()
    assert took < 58, took
    assert left == ["s2", "s3"]
    assert ends == {"s0": ("interrupted",), "s1": ("interrupted",)}   # fake_item's record after KeyboardInterrupt


# ------------------------------------------------------------------------------ summary
def test_summary_csv_and_html(tmp_path):
    rep = tmp_path / "items" / "a" / "report.html"
    rep.parent.mkdir(parents=True)
    rep.write_text("<html></html>")
    recs = [{"name": "a", "status": "done", "source": "/x/a", "seconds": 3.21,
             "metrics": {"psnr": 30.123, "verdict": "adequate", "diagnosis": "missing_effect", "top_candidate": "damping",
                         "frames_psnr": [30, 31, None, 29]},
             "outputs": {"report_html": str(rep)}},
            {"name": "b", "status": "failed", "source": "/x/b", "error": "init: /x/b: capture folder not found"}]
    write_csv(tmp_path / "s.csv", recs, tmp_path)
    rows = list(csv.DictReader(open(tmp_path / "s.csv")))
    assert [r["status"] for r in rows] == ["done", "failed"]
    assert rows[0]["psnr"] == "30.12" and rows[0]["report_html"] == "items/a/report.html"
    assert rows[1]["error"] == "init: /x/b: capture folder not found"
    write_html(tmp_path / "s.html", recs, tmp_path, title="t", totals={"items": 2})
    page = (tmp_path / "s.html").read_text()
    assert "href='items/a/report.html'" in page and "capture folder not found" in page and "damping" in page
    assert "<polyline" in page and sparkline([1.0]) == ""


def test_ray_missing_says_how_to_install(tmp_path, monkeypatch):
    from physinteract_usd.cli import main

    monkeypatch.setitem(sys.modules, "ray", None)   # import ray -> ImportError
    m = tmp_path / "m.csv"
    m.write_text("source\na\n")
    assert main(["batch", str(m), "--ray", "--workers", "2"]) == 2   # the pool's size means nothing on Ray
    code = main(["batch", str(m), "--ray"])
    assert code == 2
    assert not (tmp_path / "m.batch").exists()      # refused before anything was written
    with pytest.raises(InputError, match=r"pip install physinteract-usd\[ray\]"):
        from physinteract_usd.batch.ray_runner import import_ray

        import_ray()


def test_ray_runner_failures_and_dying_workers():
    """One Ray task per item on a local 2-CPU cluster: an exception is the item's one-line error, a
    worker that dies is retried (max_retries) and then failed, the rest go on."""
    ray = pytest.importorskip("ray", reason="Ray is an optional extra: pip install physinteract-usd[ray]")
    from physinteract_usd.batch.ray_runner import run_ray

    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])   # Ray's workers do not see tests/
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        ev = Rec()
        run_ray([("ok", {"do": "ok"}), ("raises", {"do": "raise"}), ("dies", {"do": "die"})], fake_item,
                address=None, events=ev, retries=1)
        ends = ev.ends()
        assert ends["ok"] == ("done",) and ends["raises"] == ("RuntimeError: boom",)
        assert "worker died" in ends["dies"][0] and "tried 2 times" in ends["dies"][0]
    finally:
        ray.shutdown()


def test_one_batch_at_a_time_per_output_folder(tmp_path):
    """A live batch's lock refuses a second one on the same folder; a dead one's lock is taken over."""
    from physinteract_usd import api
    from physinteract_usd.app.batch import MARKER, _acquire_lock

    m = tmp_path / "m.csv"
    m.write_text("source\nmissing\n")
    out = tmp_path / "out"
    out.mkdir()
    (out / MARKER).write_text("{}")
    (out / ".lock").write_text(str(os.getpid()))            # a live process holds it
    with pytest.raises(InputError, match="another batch"):
        api.batch(m, out=out, workers=1, progress=False, log=lambda *a: None)
    assert (out / ".lock").read_text() == str(os.getpid())   # left as it was
    (out / ".lock").write_text("999999999")                  # a process that is gone
    lock = _acquire_lock(out)
    assert lock.read_text() == str(os.getpid())


def test_the_docs_manifest_example_parses(tmp_path):
    import re
    from pathlib import Path

    from physinteract_usd.app.batch import load_manifest

    doc = (Path(__file__).resolve().parent.parent / "docs" / "batch.md").read_text()
    m = tmp_path / "manifest.csv"
    m.write_text(re.search(r"```csv\n(.*?)```", doc, re.S).group(1))
    items = load_manifest(m)
    assert [(i.name, i.kind) for i in items] == [("rope", "capture"), ("glove_b", "capture"), ("cap", "stage")]
    assert items[1].options["schedule"] == "ladder" and items[1].options["effects"] == ["damping"]
