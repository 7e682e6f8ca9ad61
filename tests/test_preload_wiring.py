"""The scan's preload on the stage (#23): `init --preload` (PhysInteractScene physinteract:preload, read back into
`SimSettings.preload`), every simulation path of `Simulation` starting from the prestressed scan (simulate, the
threads' forwards, the probes' eager twins, the tiled copies, a resumed forward) with F measured from the scan, and a
clear error where nothing holds the object."""
from __future__ import annotations

import dataclasses

import pytest
import torch

import fit_scene as fs
from capture_factory import make_capture
from test_rate_transfer_wiring import run     # the CLI's exit code, stdout, stderr
from physinteract_usd.errors import InputError
from physinteract_usd.simulation import build_simulation
from physinteract_usd.usd.stage import read_stage


def test_init_writes_the_flag_and_info_says_it(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")
    code, out, err = run(["init", tmp_path / "a.usda", "--capture", cap, "--grid", "12", "--no-preload"], capsys)
    assert code == 0, err
    assert "preload" not in out
    code, out, err = run(["init", tmp_path / "b.usda", "--capture", cap, "--grid", "12", "--preload"], capsys)
    assert code == 0, err
    assert "preloaded scan" in out
    code, out, err = run(["init", tmp_path / "c.usda", "--capture", cap, "--grid", "12"], capsys)
    assert code == 0, err
    assert "the first fit decides" in out          # neither flag: left to the fit (fit/preload_choice.py)
    a, b, c = (read_stage(tmp_path / f"{n}.usda") for n in "abc")
    assert a.settings.preload is False and b.settings.preload is True and c.settings.preload is None
    assert b.settings.to_dict()["preload"] is True and c.settings.to_dict()["preload"] is None
    assert run(["init", tmp_path / "d.usda", "--capture", cap, "--preload", "--no-preload"], capsys)[0] == 2
    # nothing holds the capture's object (no support, no ground): a simulation says so, naming the stage
    with pytest.raises(InputError, match=r"b\.usda: .*nothing holds the object.*without --preload"):
        build_simulation(b, [])
    assert build_simulation(a, []).prestress is None


@pytest.fixture(scope="module")
def bar(tmp_path_factory):
    # a light bar (50 kg/m^3): the stress that holds its scan straight on the support stays within what E_TRUE's
    # material carries (a 1000 kg/m^3 one at 5 kPa would need compressions past the fixed-corotated law's limit at
    # the support's edge, and settle there)
    sc = fs.build(tmp_path_factory.mktemp("preload") / "s", preload=True, density=50.0)
    return sc, read_stage(sc["stage"])


def test_every_simulation_path_starts_from_the_prestressed_scan(bar):
    sc, sd = bar
    still = fs.contacts(sd, lift=(0.0, 0.0, 0.0))           # the hand holds still: nothing should move
    sim = build_simulation(sd, still, dtype="float64")
    P = len(sd.particles_positions)
    nu = torch.full((P,), fs.NU_TRUE, dtype=torch.float64)
    x0 = torch.as_tensor(sd.particles_positions)
    eye = torch.eye(3, dtype=torch.float64)
    drift = []
    for E in (fs.E_TRUE, 10 * fs.E_TRUE):
        Et = torch.full((P,), E, dtype=torch.float64)
        with torch.no_grad():
            x, F = sim.simulate(Et, nu)
        drift.append(float((x - x0).abs().max()))
        assert (x - x0).abs().max() < 2e-5, E            # at rest at any E (microns)
        assert (F - eye).abs().max() < 5e-3, E           # the splats' deformation: from the scan, none
    free = build_simulation(dataclasses.replace(sd, settings=dataclasses.replace(sd.settings, preload=False)), still,
                            dtype="float64")
    with torch.no_grad():
        xf, _ = free.simulate(torch.full((P,), fs.E_TRUE, dtype=torch.float64), nu)
    assert (xf - x0).abs().max() > 20 * drift[0]         # stress-free, the bar sags from its scan (0.3 mm)


def test_the_paths_agree(bar):
    sc, sd = bar
    sim = build_simulation(sd, fs.contacts(sd), dtype="float64")
    P = len(sd.particles_positions)
    nu = torch.full((P,), fs.NU_TRUE, dtype=torch.float64)
    Es = [torch.full((P,), fs.E_TRUE * s, dtype=torch.float64) for s in (1.0, 0.9)]
    with torch.no_grad():
        ref = [sim.simulate(E, nu) for E in Es]
        each = sim.simulate_each([(E, nu, None, None) for E in Es], threads=2)
        bound = sim.rung_wanted(float(Es[0].max()))
        sim.twin_at(bound)
        at = sim.forward_at(bound, Es[0], nu)
        xb, Fb, bad = sim.simulate_batch(torch.stack(Es), nu)
        sim.simulate(Es[0], nu)
        states = sim.rollout.checkpoints()
        fr = sim.simulate_from(2, states, Es[0], nu)
    assert not bad.any()
    for i, (x, F) in enumerate(ref):
        assert torch.allclose(each[i][0], x, atol=1e-12) and torch.allclose(each[i][1], F, atol=1e-12)
        assert torch.allclose(xb[i], x, atol=1e-9) and torch.allclose(Fb[i], F, atol=1e-9)
    assert torch.allclose(at[0], ref[0][0], atol=1e-12) and torch.allclose(at[1], ref[0][1], atol=1e-12)
    assert torch.allclose(fr[0], ref[0][0], atol=1e-12) and torch.allclose(fr[1], ref[0][1], atol=1e-12)
    # the lift moves the bar: the prestressed start is not a frozen one
    assert (ref[0][0][-1] - ref[0][0][0]).abs().max() > 1e-3


def test_a_twin_under_the_same_holds_shares_the_stress_and_one_without_them_solves_its_own(bar):
    # the balance is solved once per scene, grid and holds: a probe's twin under the same support takes it (the solve
    # costs seconds at paper size); a twin without the support solves again, and nothing then holds the bar
    sc, sd = bar
    sim = build_simulation(sd, fs.contacts(sd), dtype="float64")
    twin = sim.forward_twin(fs.contacts(sd, release=2))
    assert twin.grid == sim.grid and twin.prestress is sim.prestress
    with pytest.raises(InputError, match="nothing holds the object"):
        sim.forward_twin(fs.contacts(sd)[:1])
