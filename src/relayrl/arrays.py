"""Conversions between torch tensors and NumPy arrays used across the package."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import torch

if TYPE_CHECKING:
    from numpy.typing import DTypeLike


def torch_dtype(dtype: DTypeLike) -> torch.dtype:
    """The torch dtype of a NumPy dtype (for columns allocated as tensors)."""
    return torch.from_numpy(np.zeros(0, dtype)).dtype


def as_tensor(a: np.ndarray) -> torch.Tensor:
    """`torch.as_tensor` of a NumPy array, sharing its memory where torch can: a view with a
    negative stride (a flipped image, BGR -> RGB as `img[..., ::-1]`), which torch refuses, is
    copied first."""
    if any(s < 0 for s in a.strides):
        a = a.copy()
    return torch.as_tensor(a)


def to_numpy(x: Any) -> np.ndarray:
    """A NumPy view of a CPU tensor without grad (no copy), a host copy of any other tensor,
    or `np.asarray` of anything else."""
    if isinstance(x, torch.Tensor):
        try:
            return x.numpy()
        except (RuntimeError, TypeError):
            return x.detach().cpu().numpy()
    return np.asarray(x)
