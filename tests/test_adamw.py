"""The fit's AdamW and Rprop (fit/adamw.py) are torch's, bitwise, without torch._dynamo's import (#26); the
chained optimiser of a level (the material's Rprop beside the rest's AdamW) steps each as alone (#24)."""

import pathlib
import subprocess
import sys

import pytest
import torch

from physinteract_usd.fit.adamw import AdamW, Chained, Rprop, forget_direction, make_optimizer, shrink_steps

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _run(cls, foreach):
    g = torch.Generator().manual_seed(3)
    a = torch.randn(7, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.randn(2, 3, generator=g, dtype=torch.float32, requires_grad=True)
    c = torch.randn(4, generator=g, dtype=torch.float32, requires_grad=True)
    opt = cls([{"params": [a], "lr": 1e-2}, {"params": [b, c], "lr": 3e-3}], weight_decay=0.01, foreach=foreach)
    for i in range(25):
        opt.zero_grad(set_to_none=True)
        loss = (a ** 3).sum() + (b.sin() * b).sum() + (c if i % 3 else c.detach()).exp().sum()  # c: no grad 1 in 3
        loss.backward()
        opt.step()
        for grp in opt.param_groups:       # the fit's schedules rescale lr in place
            grp["lr"] *= 0.93
        if i == 11:                        # and clear the moments in place (optimize.py's bump restore)
            for st in opt.state.values():
                st["exp_avg"].zero_()
    return [p.detach().clone() for p in (a, b, c)], opt


@pytest.mark.parametrize("foreach", [None, True, False])
def test_iterates_and_state_are_torchs_bitwise(foreach):
    (mine, o1), (theirs, o2) = _run(AdamW, foreach), _run(torch.optim.AdamW, foreach)
    for x, y in zip(mine, theirs):
        assert torch.equal(x, y)
    s1, s2 = o1.state_dict(), o2.state_dict()
    assert s1["param_groups"] == s2["param_groups"]
    for k in s2["state"]:
        for name in ("step", "exp_avg", "exp_avg_sq"):
            assert torch.equal(s1["state"][k][name], s2["state"][k][name]), (k, name)
    assert isinstance(o1, torch.optim.AdamW)



def _run_rprop(cls, foreach):
    g = torch.Generator().manual_seed(5)
    a = torch.randn(7, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.randn(2, 3, generator=g, dtype=torch.float32, requires_grad=True)
    opt = cls([{"params": [a], "lr": 0.1}, {"params": [b], "lr": 0.02}], step_sizes=(1e-3, 1.0), foreach=foreach)
    for i in range(30):
        opt.zero_grad(set_to_none=True)
        ((a - 2.0) ** 2 * torch.arange(7.0, dtype=torch.float64)).sum().backward() if i % 4 else None
        (b.sin() * b).sum().backward()
        opt.step()
    return [p.detach().clone() for p in (a, b)], opt


@pytest.mark.parametrize("foreach", [None, True, False])
def test_rprop_is_torchs_bitwise(foreach):
    (mine, o1), (theirs, o2) = _run_rprop(Rprop, foreach), _run_rprop(torch.optim.Rprop, foreach)
    for x, y in zip(mine, theirs):
        assert torch.equal(x, y)
    for k, st in o2.state_dict()["state"].items():
        for name in ("prev", "step_size"):
            assert torch.equal(o1.state_dict()["state"][k][name], st[name]), (k, name)
    assert isinstance(o1, torch.optim.Rprop)


def test_rprop_travels_where_adam_is_capped():
    # a coefficient 3 logit units from its optimum on a shallow slope: Adam moves ~its rate an iteration
    # (0.1 x 15 = 1.5 at most), Rprop's steps grow while the gradient keeps its sign (#24, foam_bar stops short)
    def travel(kind):
        p = torch.zeros(2, dtype=torch.float64, requires_grad=True)
        opt = make_optimizer([{"params": [p], "lr": 0.1}], kind)
        for _ in range(15):
            opt.zero_grad()
            (1e-3 * ((p - torch.tensor([3.0, -0.5], dtype=torch.float64)) ** 2).sum()).backward()
            opt.step()
        return p.detach()
    adam, rprop = travel("adam"), travel("rprop")
    assert float(adam[0]) < 1.6
    assert abs(float(rprop[0]) - 3.0) < 0.2 and abs(float(rprop[1]) + 0.5) < 0.2


def test_chained_steps_each_as_alone_and_the_level_helpers():
    def parts(seed):
        g = torch.Generator().manual_seed(seed)
        return (torch.randn(4, generator=g, dtype=torch.float64, requires_grad=True),
                torch.randn(3, generator=g, dtype=torch.float64, requires_grad=True))

    def loss(m, t):
        return (m.sin() * m).sum() + ((t - 1.0) ** 4).sum()

    m1, t1 = parts(1)
    ch = make_optimizer([{"params": [m1], "lr": 0.1}, {"params": [t1], "lr": 0.01}], "rprop")
    assert isinstance(ch, Chained) and len(ch.param_groups) == 2
    m2, t2 = parts(1)
    r = Rprop([{"params": [m2], "lr": 0.1}], lr=0.1, step_sizes=(1e-3, 1.0))
    a = AdamW([{"params": [t2], "lr": 0.01}], weight_decay=0.0)
    for _ in range(12):
        ch.zero_grad()
        loss(m1, t1).backward()
        ch.step()
        r.zero_grad(); a.zero_grad()
        loss(m2, t2).backward()
        r.step(); a.step()
    assert torch.equal(m1, m2) and torch.equal(t1, t2)
    st = ch.state
    assert set(map(id, st)) == {id(m1), id(t1)}
    shrink_steps(ch, 0.5)
    assert ch.param_groups[1]["lr"] == 0.005
    assert torch.equal(st[m1]["step_size"], r.state[m2]["step_size"] * 0.5)
    forget_direction(ch)
    assert not st[m1]["prev"].any() and not st[t1]["exp_avg"].any()
    assert torch.equal(st[m1]["step_size"], r.state[m2]["step_size"] * 0.25)
    with pytest.raises(ValueError, match="material_optimizer"):
        make_optimizer([{"params": [m1], "lr": 0.1}], "lbfgs")
    # the material alone: Rprop with nothing chained
    assert isinstance(make_optimizer([{"params": [m1], "lr": 0.1}], "rprop"), Chained)

def test_no_dynamo_import_and_the_fit_uses_it():
    code = ("import sys, torch\nfrom physinteract_usd.fit.adamw import AdamW\n"
            "p = torch.zeros(3, requires_grad=True)\nopt = AdamW([p], weight_decay=0.01)\n"
            "opt.zero_grad(); (p - 1).square().sum().backward(); opt.step()\n"
            "print('LOADED', sorted(m for m in ('torch._dynamo', 'sympy') if m in sys.modules), p.tolist())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "LOADED []" in out.stdout, out.stdout
    # torch's own optimiser would import torch._dynamo (and sympy) here: the saving is real
    code2 = code.replace("from physinteract_usd.fit.adamw import AdamW", "from torch.optim import AdamW")
    out2 = subprocess.run([sys.executable, "-c", code2], capture_output=True, text=True, timeout=120)
    assert out2.returncode == 0, out2.stderr
    assert "torch._dynamo" in out2.stdout, out2.stdout
    # every optimiser of the fit is this one (no torch.optim.<Optimizer>( left in the package)
    users = [p.relative_to(ROOT).as_posix() for p in (ROOT / "physinteract_usd").rglob("*.py")
             if "torch.optim." in p.read_text() and p.name != "adamw.py"]
    assert users == [], users


FIT_VERB = r"""
import sys
from physinteract_usd.cli import _main
heavy = ("torch._dynamo", "sympy", "matplotlib", "trimesh")
code = _main(["fit", sys.argv[1], "--contact-from", sys.argv[2], "--iterations", "1", "--yes"])
print("EXIT", code)
print("LOADED", sorted(m for m in heavy if m in sys.modules))
"""


def test_the_fit_verb_imports_no_dynamo_sympy_matplotlib_or_trimesh(tmp_path):
    # what a CLI fit process loads (#26): torch._dynamo came with torch's AdamW (1-4 s a process), matplotlib
    # and trimesh belong to report / mesh input, none of them to a fit of a splat capture
    sys.path.insert(0, str(ROOT / "tests"))
    import fit_scene

    case = fit_scene.build(tmp_path)
    out = subprocess.run([sys.executable, "-c", FIT_VERB, str(case["stage"]), str(case["gt"])], capture_output=True,
                         text=True, timeout=600, cwd=ROOT)
    lines = dict(line.split(" ", 1) for line in out.stdout.splitlines() if line.split(" ", 1)[0] in ("EXIT", "LOADED"))
    assert lines.get("EXIT") == "0", out.stdout[-2000:] + out.stderr[-2000:]
    assert lines["LOADED"] == "[]", lines
