"""Adam with a cosine learning-rate decay: the optimiser of every phase of the SMPL fit
(:mod:`pipeline.smpl_fit`, :mod:`pipeline.prior_correction`)."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from tqdm import tqdm


def cosine(it: int, total: int, floor: float = 0.05) -> float:
    """Learning-rate factor at iteration ``it`` of ``total``: 1 -> ``floor``."""
    return floor + (1.0 - floor) * 0.5 * (1.0 + math.cos(math.pi * it / max(total, 1)))


def adam_cosine(
    groups: list[tuple[list[torch.Tensor], float]],
    loss_fn: Callable[[], torch.Tensor],
    iterations: int,
    *,
    progress: bool,
    desc: str,
) -> float:
    """Run Adam on ``groups`` (parameters, base learning rate) for ``iterations`` steps of
    ``loss_fn()``, learning rates decayed by :func:`cosine`; returns the last loss."""
    opt = torch.optim.Adam([{"params": p, "lr": lr} for p, lr in groups])
    base = [lr for _, lr in groups]
    bar = None
    if progress:
        bar = tqdm(total=iterations, desc=desc, leave=False)
    loss = torch.zeros(())
    for it in range(iterations):
        scale = cosine(it, iterations)
        for g, lr in zip(opt.param_groups, base, strict=True):
            g["lr"] = lr * scale
        opt.zero_grad(set_to_none=True)
        loss = loss_fn()
        loss.backward()
        opt.step()
        if bar is not None:
            bar.update()
            if it % 20 == 0:
                bar.set_postfix(loss=f"{loss.item():.3g}")
    if bar is not None:
        bar.close()
    return float(loss.detach())
