"""Adam with a cosine learning-rate decay: the optimiser of every phase of the SMPL fit
(:mod:`pipeline.fit.smpl`, :mod:`pipeline.fit.prior_correction`)."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch.optim.adam import adam as torch_adam  # the function Adam.step calls

from pipeline.core.progress import Progress, StageBar


def cosine(it: int, total: int, floor: float = 0.05) -> float:
    """Learning-rate factor at iteration ``it`` of ``total``: 1 -> ``floor``."""
    return floor + (1.0 - floor) * 0.5 * (1.0 + math.cos(math.pi * it / max(total, 1)))


def adam_cosine(
    groups: list[tuple[list[torch.Tensor], float]],
    loss_fn: Callable[[], torch.Tensor],
    iterations: int,
    *,
    progress: Progress,
    desc: str,
) -> float:
    """Run Adam on ``groups`` (parameters, base learning rate) for ``iterations`` steps of
    ``loss_fn()``, learning rates decayed by :func:`cosine`; returns the last loss.
    ``progress`` (:mod:`pipeline.core.progress`) hears of every step as stage ``desc``.

    The steps are torch's own Adam (``torch.optim.adam.adam``, the function
    ``torch.optim.Adam.step`` calls, with its defaults), the same numbers bit for bit
    (tests/pipeline/test_fit_optim.py), without the ``torch.optim.Adam`` object: its
    constructor and ``zero_grad`` import ``torch._dynamo`` on first use (~1 s and
    sympy, in every process that fits, the ``mvviz run`` and each batch worker alike),
    which the fit, never compiled, has no use for."""
    params = [list(ps) for ps, _ in groups]
    state = [
        [(torch.zeros_like(p), torch.zeros_like(p), torch.tensor(0.0)) for p in ps] for ps in params
    ]
    loss = torch.zeros(())
    with StageBar(desc, iterations, progress, leave=False) as bar:
        for it in range(iterations):
            scale = cosine(it, iterations)
            for ps in params:
                for p in ps:
                    p.grad = None
            loss = loss_fn()
            loss.backward()
            with torch.no_grad():
                for ps, st, (_, lr) in zip(params, state, groups, strict=True):
                    _adam_step(ps, st, lr * scale)
            bar.update()
            if it % 20 == 0 and progress is True:
                bar.set_postfix(loss=f"{loss.item():.3g}")
    return float(loss.detach())


def _adam_step(
    params: list[torch.Tensor],
    state: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]],
    lr: float,
) -> None:
    """One step of torch's Adam (its defaults: betas 0.9 / 0.999, eps 1e-8, no weight
    decay) on the parameters with a gradient; ``state``: each parameter's first and
    second moments and step count, updated in place."""
    have = [i for i, p in enumerate(params) if p.grad is not None]
    if not have:
        return
    torch_adam(
        [params[i] for i in have],
        [params[i].grad for i in have],
        [state[i][0] for i in have],
        [state[i][1] for i in have],
        [],
        [state[i][2] for i in have],
        amsgrad=False, beta1=0.9, beta2=0.999, lr=lr, weight_decay=0.0, eps=1e-8,
        maximize=False,
    )  # fmt: skip
