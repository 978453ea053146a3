"""Conversions between torch tensors and NumPy arrays used across the package."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch


def torch_dtype(dtype: np.dtype) -> torch.dtype:
    """The torch dtype of a NumPy dtype (for columns allocated as tensors)."""
    return torch.from_numpy(np.zeros(0, dtype)).dtype


def to_numpy(x: Any) -> np.ndarray:
    """A NumPy view of a CPU tensor without grad (no copy), a host copy of any other tensor,
    or `np.asarray` of anything else."""
    if isinstance(x, torch.Tensor):
        try:
            return x.numpy()
        except (RuntimeError, TypeError):
            return x.detach().cpu().numpy()
    return np.asarray(x)
