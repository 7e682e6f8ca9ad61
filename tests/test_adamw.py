"""The fit's AdamW (fit/adamw.py) is torch's, bitwise, without torch._dynamo's import (#26)."""

import pathlib
import subprocess
import sys

import pytest
import torch

from physinteract_usd.fit.adamw import AdamW

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
