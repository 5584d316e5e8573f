"""One context manager for torch's intra-op thread count: the fit, the synthesis and the
restoration each pick the count that measures best for their small tensors, and must
leave the caller's setting as they found it."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch


@contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Torch's intra-op threads set to ``n`` (0: left alone) inside, restored after."""
    old = torch.get_num_threads()
    if n > 0:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)
