"""`export --sim-ready` of a preloaded scan (#23): the twin's rest is its unloaded shape, so that a simulator taking
the file's points as its rest (Newton) settles it back into the scan under gravity instead of sagging it a second
time. `tetmesh.unloaded_points` against exact answers; the whole export in Newton (a simulator we did not write)."""
import dataclasses

import numpy as np
import pytest

import fit_scene as fs
from physinteract_usd import api
from physinteract_usd import tetmesh as tm
from physinteract_usd.app.simready import build_sim_ready
from physinteract_usd.usd.simready import write_sim_ready
from test_simready import _newton, lattice_box


def test_a_uniform_stretch_is_undone_exactly():
    # a box stretched 1.2x along x from its held face x = 0 (and turned by nothing): its unloaded rest is x / 1.2
    h = 0.01
    mesh = tm.tetmesh_from_particles(lattice_box((8, 3, 3), h), h)
    x = mesh.points[:, 0]
    held = x <= x.min() + 1e-9
    G = np.tile(np.diag([1 / 1.2, 1.0, 1.0]), (len(mesh.tets), 1, 1))
    rest = tm.unloaded_points(mesh, G, held)
    want = mesh.points.copy()
    want[:, 0] = x.min() + (x - x.min()) / 1.2
    assert np.abs(rest - want).max() < 1e-9


def test_a_bent_bar_unbends_through_its_rotations():
    # known answer: a bar bent down into an arc of curvature k about a centre below it (x along it; each fibre at
    # height y above the middle stretched by 1 + k y, as a sagging cantilever's top is) unloads to the straight bar:
    # the stretches alone say it, the arc's rotations found with the rest
    h, k = 0.005, 4.0
    straight = tm.tetmesh_from_particles(lattice_box((24, 4, 3), h), h)
    p = straight.points
    ym = p[:, 1].mean()
    yc = p[:, 1] - ym
    th = k * (p[:, 0] - p[:, 0].min())                  # the arc: angle k x, radius 1/k + y about (x0, ym - 1/k)
    bent = np.stack([p[:, 0].min() + np.sin(th) * (1 / k + yc), ym - 1 / k + np.cos(th) * (1 / k + yc), p[:, 2]], 1)
    mesh = tm.TetMesh(points=bent, tets=straight.tets, surface=straight.surface)
    F = mesh.edges() @ np.linalg.inv(straight.edges())  # each tetrahedron's map, straight -> bent: R V
    U, S, _ = np.linalg.svd(F)
    G = np.linalg.inv(np.einsum("tij,tj,tkj->tik", U, S, U))     # V^-1: its stretch undone, its rotation not given
    assert np.abs(G - np.eye(3)).max() > 0.03           # fibres stretched and shortened by ~4% (k x half the height)
    held = p[:, 0] <= p[:, 0].min() + 1e-9
    rest = tm.unloaded_points(mesh, G, held)
    assert np.abs(rest - p).max() < 0.05 * np.abs(bent - p).max(), (np.abs(rest - p).max(), np.abs(bent - p).max())


def test_newton_settles_the_preloaded_twin_back_into_the_scan(tmp_path):
    # the tiny bar's scan taken as carrying its weight on its clamp (init --preload); exported, Newton lets gravity act
    # on it from the file's rest alone. Taken as the rest (the export before this), it sags away from the scan
    # (max 23 mm, mean 7.3 mm when measured); from its unloaded rest it settles back near the scan (7.7 / 1.4 mm:
    # Newton's tetrahedra and our MPM are not the same discretisation)
    _newton()
    from physinteract_usd.crosscheck import Load, run_newton

    b = fs.build(tmp_path / "bar", E=5e3, density=200.0, n_frames=4, preload=True, e_range=(5e2, 5e4))
    api.fit(b["stage"], iterations=1, contact_from=b["gt"], progress=False, log=lambda *a: None,
            settings_overrides=dict(fs.SMOKE_SETTINGS, levels=(1,), level_share=(1.0,), confidence_probes=0))
    sd = api.read_scene(b["stage"])
    scan = tm.tetmesh_from_particles(sd.particles_positions, sd.settings.particle_spacing).points
    err, info = {}, {}
    for pre in (True, False):
        a = build_sim_ready(dataclasses.replace(sd, settings=dataclasses.replace(sd.settings, preload=pre)),
                            log=lambda *m: None)
        info[pre] = a.info
        held = np.concatenate([h.vertices for h in a.supports])
        assert np.abs(a.points[held] - scan[held]).max() < 1e-12          # the clamp where the scan has it
        out = tmp_path / f"twin_{pre}.usda"
        write_sim_ready(out, a)
        r = run_newton(out, Load("sag", np.zeros(3), 0.0, duration=0.6, damping=60.0))
        err[pre] = np.linalg.norm(r["final"] - scan, axis=1)
    assert info[True]["restShape"].startswith("unloaded") and info[False]["restShape"] == "scan"
    assert info[True]["unloadedShift"]["max_m"] > 0.01
    assert err[False].max() > 0.015                                       # the scan as rest: it sags again
    assert err[True].mean() < 0.3 * err[False].mean() and err[True].max() < 0.5 * err[False].max(), \
        (err[True].mean(), err[False].mean(), err[True].max(), err[False].max())


def test_a_block_compressed_on_the_ground_stands_up_again():
    # known answer: a block of height H resting on the ground, compressed under its weight (nu = 0: each layer at
    # height y shortened by rho g (H - y) / E), its bottom layer held where the scan has it: the unloaded rest is the
    # block at full height, exactly (a compatible stretch without rotations)
    h, H, c = 0.01, 0.08, 0.05                       # c = rho g H / E: 5% at the bottom
    rest = tm.tetmesh_from_particles(lattice_box((4, 8, 4), h), h)
    y = rest.points[:, 1] - rest.points[:, 1].min()
    sink = c * (y - y ** 2 / (2 * H))                 # the integral of the strain c (1 - y / H) from the bottom
    scan = rest.points.copy()
    scan[:, 1] -= sink
    mesh = tm.TetMesh(points=scan, tets=rest.tets, surface=rest.surface)
    F = mesh.edges() @ np.linalg.inv(rest.edges())
    G = np.linalg.inv(0.5 * (F + np.transpose(F, (0, 2, 1))))
    held = y <= 1e-9
    back = tm.unloaded_points(mesh, G, held)
    assert sink.max() > 1.5e-3
    assert np.abs(back - rest.points).max() < 0.02 * sink.max()


def test_a_preloaded_scan_nothing_holds_is_one_line_and_writes_nothing(tmp_path, capsys):
    from capture_factory import make_capture
    from physinteract_usd.cli import main

    cap = make_capture(tmp_path / "cap")
    stage = tmp_path / "s.usda"
    assert main(["init", str(stage), "--capture", str(cap), "--grid", "12", "--preload"]) == 0
    before = stage.read_bytes()
    capsys.readouterr()
    assert main(["export", str(stage), str(tmp_path / "twin.usdc"), "--sim-ready"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "s.usda" in err[0] and "nothing holds the object" in err[0], err
    assert err[0].count("s.usda") == 1
    assert stage.read_bytes() == before and not (tmp_path / "twin.usdc").exists()
