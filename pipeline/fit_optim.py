"""Adam with a cosine learning-rate decay: the optimiser of every phase of the SMPL fit
(:mod:`pipeline.smpl_fit`, :mod:`pipeline.prior_correction`)."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from pipeline.progress import Progress, StageBar


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
    ``progress`` (:mod:`pipeline.progress`) hears of every step as stage ``desc``."""
    opt = torch.optim.Adam([{"params": p, "lr": lr} for p, lr in groups])
    base = [lr for _, lr in groups]
    loss = torch.zeros(())
    with StageBar(desc, iterations, progress, leave=False) as bar:
        for it in range(iterations):
            scale = cosine(it, iterations)
            for g, lr in zip(opt.param_groups, base, strict=True):
                g["lr"] = lr * scale
            opt.zero_grad(set_to_none=True)
            loss = loss_fn()
            loss.backward()
            opt.step()
            bar.update()
            if it % 20 == 0 and progress is True:
                bar.set_postfix(loss=f"{loss.item():.3g}")
    return float(loss.detach())
