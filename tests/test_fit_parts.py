"""The "parts" step of the select schedule (fit/select.py, fit/regions.py): candidate parts by
appearance and by motion, each part's E by a coordinate sweep, the polish's gradient.

Known answers on small synthetic inputs (no simulation, or the tiny bar of tests/fit_scene.py in
float64 for the gradient); the whole schedule's known answers (two-part bar -> parts, uniform bar
-> uniform) are in tests/test_fit_select.py."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from physinteract_usd.fit import regions as R
from physinteract_usd.fit.optimize import FitSettings
from physinteract_usd.fit.select import part_sweep

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _bar(n=(24, 4, 4), step=0.01):
    """Particles on a lattice along x (a bar) and their graph."""
    g = np.stack(np.meshgrid(*[np.arange(k) * step for k in n], indexing="ij"), -1).reshape(-1, 3)
    return g, R.particle_graph(g, 1.6 * step)


def test_colour_clusters_two_colours_three_colours_and_one():
    x, _ = _bar()
    rng = np.random.default_rng(0)
    free = np.ones(len(x), bool)
    two = np.where((x[:, 0] < 0.12)[:, None], [0.2, 0.3, 0.8], [0.9, 0.7, 0.2]) + rng.normal(0, 0.02, (len(x), 3))
    lab = R.colour_clusters(two, free)
    assert lab is not None and len(np.unique(lab)) == 2
    assert R.same_partition(lab, (x[:, 0] < 0.12).astype(int))
    three = np.select([x[:, 0] < 0.08, x[:, 0] < 0.16], [0, 1], 2)
    col = np.array([[0.2, 0.3, 0.8], [0.9, 0.7, 0.2], [0.1, 0.8, 0.1]])[three] + rng.normal(0, 0.02, (len(x), 3))
    lab3 = R.colour_clusters(col, free)
    assert lab3 is not None and R.same_partition(lab3, three)
    # one colour with texture noise: no parts
    assert R.colour_clusters(np.full((len(x), 3), 0.5) + rng.normal(0, 0.02, (len(x), 3)), free) is None
    # held particles take no cluster
    held = x[:, 0] < 0.02
    lab = R.colour_clusters(two, ~held)
    assert (lab[held] == -1).all() and (lab[~held] >= 0).all()


def test_connected_parts_split_pieces_merge_small_ones_and_cap_the_count():
    x, g = _bar()
    # cluster 0 at both ends, cluster 1 in the middle: three connected parts
    cl = np.where((x[:, 0] < 0.06) | (x[:, 0] > 0.17), 0, 1)
    lab = R.connected_parts(cl, g, min_size=8, max_parts=4)
    assert len(np.unique(lab)) == 3
    assert R.same_partition(lab, np.select([x[:, 0] < 0.06, x[:, 0] > 0.17], [0, 2], 1))
    # a piece smaller than min_size joins its neighbour
    cl = np.where(x[:, 0] < 0.005, 1, 0)          # one slice of 16 particles
    assert R.connected_parts(cl, g, min_size=20, max_parts=4) is None     # then one part only
    cl2 = np.where(x[:, 0] < 0.005, 1, np.where(x[:, 0] > 0.115, 2, 0))
    lab = R.connected_parts(cl2, g, min_size=20, max_parts=4)
    assert len(np.unique(lab)) == 2 and lab[x[:, 0] < 0.005][0] == lab[np.argmin(np.abs(x[:, 0] - 0.05))]
    # more connected parts than allowed: one part per cluster
    cl = np.where((x[:, 0] < 0.06) | (x[:, 0] > 0.17), 0, 1)
    lab = R.connected_parts(cl, g, min_size=8, max_parts=2)
    assert R.same_partition(lab, cl)


def test_motion_clusters_split_where_the_score_changes_sign():
    x, g = _bar()
    rng = np.random.default_rng(1)
    score = np.where(x[:, 0] < 0.10, -1.0, 1.0) + rng.normal(0, 0.3, len(x))
    lab = R.motion_clusters(score, np.ones(len(x), bool), g)
    truth = (x[:, 0] >= 0.10).astype(int)
    assert np.mean(lab == truth) > 0.9


class _Separable:
    """A stand-in for PartProbe: a loss that is a sum of one curve per part's log E, part 1's
    curve with two wells (a shallow one at 3e5 Pa, where a start from the uniform optimum sits,
    and the deeper one at the truth); counts its probes."""

    def __init__(self, labels, target, second):
        self.labels, self.target, self.second = np.asarray(labels), np.asarray(target, float), float(second)
        self.cache = {}

    def __call__(self, le):
        le = np.asarray(le, float)
        v = 0.01 + 0.02 * math.tanh((le[0] - self.target[0]) ** 2)
        v += min(0.01 + 0.02 * math.tanh((le[1] - self.target[1]) ** 2 / 1.0),
                 0.015 + 0.02 * math.tanh((le[1] - self.second) ** 2 / 0.3))
        self.cache[tuple(le)] = v
        return v

    def many(self, les):
        return None


def test_part_sweep_finds_each_part_from_a_start_in_the_wrong_well():
    labels = np.r_[np.zeros(30, int), np.ones(20, int)]
    target = np.log([1e5, 1e4])
    f = _Separable(labels, target, second=math.log(3e5))
    grid = np.linspace(math.log(1e3), math.log(1e7), 7)
    s = FitSettings(search_evals=8, select_part_rounds=2)
    r = part_sweep(f, np.full(2, math.log(3e5)), grid, s)     # part 1 starts in its shallow well
    assert np.all(np.abs(r["log_e"] - target) < math.log(1.2)), np.exp(r["log_e"])
    assert r["loss"] < 0.021 and set(r["lines"]) == {0, 1}
    # a probe budget of (points + golden) per part and round, not a grid over all parts
    assert len(f.cache) <= 2 * (7 + 8) + 2 * 8 + 1


class _Valley:
    """A stand-in for PartProbe: two parts' loss a narrow valley across the axes (raising one
    part's log E and lowering the other's moves along its floor, as a softer hand-side part and a
    stiffer clamp-side part move a bar's tip alike), its minimum at `target`."""

    def __init__(self, target):
        self.target, self.cache = np.asarray(target, float), {}
        self.labels = np.r_[np.zeros(30, int), np.ones(20, int)]

    def __call__(self, le):
        d = np.asarray(le, float) - self.target
        across, along = (d[0] + d[1]) / math.sqrt(2), (d[0] - d[1]) / math.sqrt(2)
        v = 0.01 + 0.02 * math.tanh(across ** 2 / 0.002 + along ** 2 / 0.2)
        self.cache[tuple(np.round(le, 10))] = v
        return v

    def many(self, les):
        return None


def test_part_refine_follows_a_valley_across_the_axes_to_its_minimum():
    """From a point on the valley's floor 1.45x / 0.69x off (where the two-part bar's coordinate
    sweep stopped: 10.9 / 76.2 kPa for 10 / 100 kPa), the simplex reaches each part within 5% in at
    most 24 probes; the coordinate search (one part at a time), with more probes, does not."""
    from physinteract_usd.fit.select import part_refine

    target = np.log([1e4, 1e5])
    start = target + np.log([1.45, 1 / 1.45])
    f = _Valley(target)
    r = part_refine(f, start, math.log(1e3), math.log(1e7), 24)
    assert np.all(np.abs(r["log_e"] - target) < math.log(1.05)), np.exp(r["log_e"])
    assert r["loss"] < f(start) and 0 < r["probes"] <= 26, r
    # the coordinate search (a whole-range line per part, then local golden sections): stalls
    g = _Valley(target)
    grid = np.linspace(math.log(1e3), math.log(1e7), 7)
    c = part_sweep(g, start, grid, FitSettings(search_evals=5, select_part_rounds=4))
    assert len(g.cache) > 24 and np.max(np.abs(c["log_e"] - target)) > math.log(1.2), (len(g.cache), np.exp(c["log_e"]))
    # no budget, or a start at the bound: nothing breaks, nothing gets worse
    assert part_refine(f, start, math.log(1e3), math.log(1e7), 2)["probes"] == 0
    edge = part_refine(_Valley(np.log([1e3, 1e5])), np.log([1e3, 2e5]), math.log(1e3), math.log(1e7), 24)
    assert edge["log_e"][0] >= math.log(1e3) - 1e-12 and edge["loss"] <= _Valley(np.log([1e3, 1e5]))(np.log([1e3, 2e5]))


def test_part_log_e_gradient_matches_finite_differences_float64(tmp_path):
    """d loss / d (each part's log E) through the one-hot basis and the simulator (float64, the
    tiny bar) against central differences."""
    import fit_scene as fs
    from physinteract_usd.app.fit import prepare_fit
    from physinteract_usd.fit import FitProblem
    from physinteract_usd.fit.material import MaterialField

    b = fs.build(tmp_path / "bar")
    job = prepare_fit(b["stage"], iterations=1, contact_from=b["gt"], joint=False, log=lambda *a: None)
    prob = FitProblem(job.scene, job.observations, job.contacts, dtype="float64")
    st = prob.scene.settings
    labels = (prob.x0[:, 0] > np.median(prob.x0[:, 0])).astype(np.int64)
    mat = MaterialField(prob.x0, (st.youngs_min, st.youngs_max), st.poisson_max, dtype=torch.float64)
    mat.set_uniform(4e3, 0.3)
    mat.set_regions(labels)
    mat.set_region_log_e(np.log([3e3, 8e3]))
    nu = mat.poisson().detach()

    def loss(theta):
        mat.theta = theta
        return prob.loss(mat.youngs(), nu)["rec"]

    th = mat.theta.detach().clone().requires_grad_(True)
    g, = torch.autograd.grad(loss(th), th)
    h = 1e-4
    for j in range(2):
        d = torch.zeros_like(th)
        d[j] = h
        with torch.no_grad():
            fd = (float(loss(th.detach() + d)) - float(loss(th.detach() - d))) / (2 * h)
        assert abs(float(g[j]) - fd) <= 1e-4 * max(abs(fd), 1e-6) + 1e-9, (j, float(g[j]), fd)


def test_colour_clusters_do_not_take_the_blend_along_an_edge_for_a_third_colour():
    """Local mean colours blend across the edge between two parts: a band of in-between colours
    is not a third part."""
    x, _ = _bar((40, 4, 4))
    t = np.clip((x[:, 0] - 0.17) / 0.06, 0, 1)[:, None]          # a blend 6 particles wide
    col = (1 - t) * np.array([0.2, 0.3, 0.8]) + t * np.array([0.9, 0.7, 0.2])
    lab = R.colour_clusters(col + np.random.default_rng(2).normal(0, 0.01, col.shape), np.ones(len(x), bool))
    assert lab is not None and len(np.unique(lab)) == 2


@pytest.mark.slow      # ~120 s of CPU (measured on the shared 2-core VM: 7 min wall under load)
def test_parts_step_recovers_a_two_part_bar_from_the_uniform_optimum(tmp_path, monkeypatch):
    """The parts step alone (`select.parts_stage`) on the two-part bar of tests/test_fit_select.py
    (clamped half 100 kPa, lifted half 10 kPa, two colours), started from a uniform model at the
    uniform loss's optimum (~2e5 Pa, in neither part's well): the appearance candidate is the two
    halves and each part's E comes out within 5% (measured: the coordinate sweep 9.91 / 94.7 kPa,
    the simplex over both 9.97 / 100.1 kPa; the whole schedule: test_fit_select.py)."""
    import types

    import test_fit_select as tfs
    from physinteract_usd.app.fit import prepare_fit
    from physinteract_usd.fit import FitProblem
    from physinteract_usd.fit.select import FrameView, holdout_frames, parts_stage

    b, stiff = tfs._two_part_bar(tmp_path / "two", 1e4, monkeypatch, e_range=(3e3, 3e5))
    job = prepare_fit(b["stage"], iterations=1, contact_from=b["gt"], joint=False, log=lambda *a: None)
    prob = FitProblem(job.scene, job.observations, job.contacts)
    train, _ = holdout_frames(prob.T, 3, keep=[5])
    view = FrameView(prob, train)
    P = len(prob.x0)
    names = prob.sim.slot_names()
    ru = types.SimpleNamespace(youngs=np.full(P, 2e5), poisson=np.full(P, fs_nu()), effect_parameters={},
                               trajectories={n: t.cpu().numpy() for n, t in zip(names, prob.initial_trajectories())})
    s = FitSettings(select_part_points=7, search_evals=4, select_part_rounds=2, lr_material=0.1, joint=False)
    rp, rec = parts_stage(prob, view, s, {"minima": []}, ru, 2)
    assert rp is not None and rec["kind"] == "appearance", rec
    assert R.same_partition(rp.regions, stiff.astype(int))
    e = rp.youngs
    held = np.asarray(prob.held_particles(), bool)
    e_stiff, e_soft = float(np.median(e[stiff & ~held])), float(np.median(e[~stiff]))
    assert abs(e_soft / 1e4 - 1) < 0.05 and abs(e_stiff / 1e5 - 1) < 0.05, (e_stiff, e_soft, rec)
    assert rec["refine"]["loss"] <= rec["refine"]["from_loss"] and rec["refine"]["probes"] > 0, rec["refine"]


def fs_nu():
    import fit_scene as fs

    return fs.NU_TRUE
