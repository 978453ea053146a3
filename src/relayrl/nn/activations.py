"""The activation registry: every form of an activation in one record.

An MLP's autograd forward uses `torch`; the inference path uses `inplace` (torch) or `numpy`;
the hand-written gradients (mlp_fast.py) use `backward`, which needs either the output h
(relu, leaky_relu, tanh) or the pre-activation z (elu, silu, gelu: `needs_input`). Adding an
activation is one entry here; the config keys' choices are this registry's names.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

Tensor = torch.Tensor
_aten = torch.ops.aten


@dataclass(frozen=True)
class Activation:
    name: str
    torch: Callable[[Tensor], Tensor]
    inplace: Callable[[Tensor], Tensor]  # may overwrite its argument (torch has no in-place gelu)
    numpy: Callable[[np.ndarray], np.ndarray]  # may overwrite its argument; callers use the result
    # d loss / d z from g = d loss / d h, given z (None unless `needs_input`) and h = act(z),
    # with the kernels autograd calls, so values equal autograd's. Written into g (the
    # hand-written backward passes hand in a fresh gradient): no new tensor per layer.
    backward: Callable[[Tensor, Tensor | None, Tensor], Tensor]
    needs_input: bool = False  # backward reads z: a forward that saves for it must not overwrite z


# Named functions, not lambdas: the modules that hold them (a loaded policy's) pickle by name.
def _relu_numpy(x: np.ndarray) -> np.ndarray:
    return np.maximum(x, 0.0, out=x)


def _relu_backward(g: Tensor, z: Tensor | None, h: Tensor) -> Tensor:
    return _aten.threshold_backward.grad_input(g, h, 0, grad_input=g)


def _tanh_numpy(x: np.ndarray) -> np.ndarray:
    return np.tanh(x, out=x)


def _tanh_backward(g: Tensor, z: Tensor | None, h: Tensor) -> Tensor:
    return _aten.tanh_backward.grad_input(g, h, grad_input=g)


def _elu_numpy(x: np.ndarray) -> np.ndarray:
    return np.where(x > 0, x, np.expm1(np.minimum(x, 0.0)))


def _elu_backward(g: Tensor, z: Tensor | None, h: Tensor) -> Tensor:
    return _aten.elu_backward.grad_input(g, 1.0, 1, 1, False, z, grad_input=g)


LEAKY_SLOPE = 0.01  # torch's and Keras's default negative slope


def _leaky_relu(x: Tensor) -> Tensor:
    return F.leaky_relu(x, LEAKY_SLOPE)


def _leaky_relu_(x: Tensor) -> Tensor:
    return F.leaky_relu_(x, LEAKY_SLOPE)


def _leaky_relu_numpy(x: np.ndarray) -> np.ndarray:
    return np.maximum(x, x * np.float32(LEAKY_SLOPE), out=x)  # the slope is below 1


def _leaky_relu_backward(g: Tensor, z: Tensor | None, h: Tensor) -> Tensor:
    # h > 0 exactly where z > 0 (a positive slope), so the output stands in for the input
    return _aten.leaky_relu_backward.grad_input(g, h, LEAKY_SLOPE, True, grad_input=g)


def _silu_(x: Tensor) -> Tensor:
    return F.silu(x, inplace=True)


def _silu_numpy(x: np.ndarray) -> np.ndarray:
    # torch's kernel: NumPy's exp overflows (with a warning) for large negative inputs
    return F.silu(torch.from_numpy(x), inplace=True).numpy()


def _silu_backward(g: Tensor, z: Tensor | None, h: Tensor) -> Tensor:
    return _aten.silu_backward.grad_input(g, z, grad_input=g)


def _gelu_numpy(x: np.ndarray) -> np.ndarray:
    return F.gelu(torch.from_numpy(x)).numpy()  # NumPy has no erf


def _gelu_backward(g: Tensor, z: Tensor | None, h: Tensor) -> Tensor:
    return _aten.gelu_backward.grad_input(g, z, grad_input=g)


ACTIVATIONS: dict[str, Activation] = {a.name: a for a in (
    Activation("relu", torch.relu, torch.relu_, _relu_numpy, _relu_backward),
    Activation("tanh", torch.tanh, torch.tanh_, _tanh_numpy, _tanh_backward),
    Activation("elu", F.elu, F.elu_, _elu_numpy, _elu_backward, needs_input=True),
    Activation("leaky_relu", _leaky_relu, _leaky_relu_, _leaky_relu_numpy, _leaky_relu_backward),
    Activation("silu", F.silu, _silu_, _silu_numpy, _silu_backward, needs_input=True),
    Activation("gelu", F.gelu, F.gelu, _gelu_numpy, _gelu_backward, needs_input=True),
)}
