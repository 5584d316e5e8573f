"""pipeline.fit.optim: the fit's Adam steps are torch.optim.Adam's, bit for bit, and
fitting imports no torch._dynamo."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch

from pipeline.fit.optim import adam_cosine, cosine


def _problem(seed: int):
    """Two groups of parameters (one unused by the loss some steps: no gradient) and a
    non-convex loss of them."""
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(5, 3, generator=g, dtype=torch.float64).requires_grad_()
    b = torch.randn(7, generator=g, dtype=torch.float64).requires_grad_()
    c = torch.randn(2, generator=g, dtype=torch.float64).requires_grad_()
    target = torch.randn(5, 3, generator=g, dtype=torch.float64)
    return [([a, b], 0.05), ([c], 0.2)], (a, b, c, target)


def _loss(a, b, c, target):
    def loss():
        return (
            torch.nn.functional.smooth_l1_loss(a * torch.sin(b[:3]), target)
            + (b**2).sum() * 1e-2
            + torch.cos(c).sum()
        )

    return loss


def _reference(groups, loss_fn, iterations):
    """torch.optim.Adam with the same cosine decay: what adam_cosine did before."""
    opt = torch.optim.Adam([{"params": p, "lr": lr} for p, lr in groups])
    base = [lr for _, lr in groups]
    for it in range(iterations):
        for group, lr in zip(opt.param_groups, base, strict=True):
            group["lr"] = lr * cosine(it, iterations)
        opt.zero_grad(set_to_none=True)
        loss = loss_fn()
        loss.backward()
        opt.step()
    return float(loss.detach())


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_adam_cosine_matches_torch_optim_adam_bit_for_bit(seed):
    groups, (a, b, c, t) = _problem(seed)
    ours = adam_cosine(groups, _loss(a, b, c, t), 40, progress=False, desc="test")
    ref_groups, (ra, rb, rc, rt) = _problem(seed)
    ref = _reference(ref_groups, _loss(ra, rb, rc, rt), 40)
    assert ours == ref
    for mine, theirs in zip((a, b, c), (ra, rb, rc), strict=True):
        assert torch.equal(mine, theirs)
    # and the parameters moved (a test that cannot pass on a no-op)
    assert not torch.equal(a, _problem(seed)[1][0])


def test_adam_cosine_skips_parameters_without_a_gradient():
    groups, (a, b, c, t) = _problem(3)
    unused = torch.ones(4, requires_grad=True)
    groups.append(([unused], 1.0))
    ref_groups, (ra, rb, rc, rt) = _problem(3)
    ref_unused = torch.ones(4, requires_grad=True)
    ref_groups.append(([ref_unused], 1.0))
    assert adam_cosine(groups, _loss(a, b, c, t), 10, progress=False, desc="t") == _reference(
        ref_groups, _loss(ra, rb, rc, rt), 10
    )
    assert torch.equal(unused, torch.ones(4)) and torch.equal(c, rc)


@pytest.mark.slow
def test_fitting_does_not_import_torch_dynamo():
    code = (
        "import sys\n"
        "from tests.pipeline.test_fit_optim import _loss, _problem\n"
        "from pipeline.fit.optim import adam_cosine\n"
        "groups, args = _problem(0)\n"
        "adam_cosine(groups, _loss(*args), 3, progress=False, desc='t')\n"
        "print('torch._dynamo' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        cwd=Path(__file__).resolve().parents[2],
    ).stdout
    assert out.strip() == "False"
