"""A network's train / eval mode where it acts and is evaluated: a user's encoder may hold
Dropout or BatchNorm, which act otherwise in each mode (built-in networks hold neither)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from torch import nn


@contextlib.contextmanager
def evaluating(module: nn.Module) -> Iterator[nn.Module]:
    """`module` in eval mode inside (Dropout off, BatchNorm on its running statistics, which it
    leaves as they are), each submodule's own mode put back after, as Stable-Baselines3 acts and
    evaluates (`set_training_mode(False)`)."""
    modes = [(m, m.training) for m in module.modules()]
    module.eval()
    try:
        yield module
    finally:
        for m, training in modes:
            m.training = training
