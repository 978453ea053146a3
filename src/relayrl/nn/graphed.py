"""A gradient step (or a policy's forward pass) replayed from a CUDA graph: one launch instead of
the hundred-odd kernels of a forward, backward and optimizer step, whose launch latency bounds
small RL updates on a GPU.

`GraphedStep(step)` runs `step(*tensors)` as it is for its first `WARMUP` calls of each input
signature (which shapes, dtypes and which inputs are None), on a side stream as capture
requires; the next call captures it and every later one copies its inputs into the captured
buffers and replays. Every call is one real step: the captured call replays once captured.

What a step may do: work on tensors already on the device, update parameters and optimizer
state in place (`optim.FastAdam` keeps its learning rate in a device tensor there, so a
schedule reaches the replays), draw noise from generators named at construction. What it may
not: read a tensor's value on the host (`.item()`, `float(t)`, a Python branch on a value) or
allocate tensors it keeps across calls. The returned tensors are the graph's own outputs,
overwritten by the next call: read them before the next step (the learner does).

`RELAYRL_CUDA_GRAPHS=0` turns capture off (the same steps, each launched kernel by kernel);
benchmarks compare the two.

`compiled(losses)`: an update's loss function (forward pass and losses; the backward pass and
the optimizer step stay outside) through `torch.compile(fullgraph=True)` where `RELAYRL_COMPILE`
asks for it: inductor fuses its elementwise ops, so a captured step holds several times fewer
kernels. Off by default: compiling costs seconds per process (tens with a cold cache) and needs
a C++ compiler on a CPU; `RELAYRL_COMPILE=1` turns it on for every update's losses (inductor),
another value names a `torch.compile` backend (tests use `aot_eager`).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import NamedTuple, TypeVar

import torch

from relayrl.errors import UserError

Tensor = torch.Tensor
Signature = tuple[tuple[torch.Size, torch.dtype, torch.device] | None, ...]
WARMUP = 3  # eager calls per signature before capture (lazy cuBLAS / autograd set-up)
RECOMPILE_LIMIT = 64  # compiled variants of one loss function a process may hold (see `compiled`)
F = TypeVar("F", bound=Callable)


def cuda_graphs_enabled(device: torch.device) -> bool:
    """True where steps on `device` are captured: a CUDA device and `RELAYRL_CUDA_GRAPHS` 1 (the
    default) rather than 0; another value is one line, not a setting left on without a word."""
    setting = os.environ.get("RELAYRL_CUDA_GRAPHS", "1")
    if setting not in ("0", "1"):
        raise UserError(f"RELAYRL_CUDA_GRAPHS={setting!r} is not valid; valid: 1 (capture CUDA graphs, the default) "
                        "or 0 (launch each kernel)")
    return device.type == "cuda" and setting == "1"


def compiled(losses: F) -> F:
    """`losses` through `torch.compile` where `RELAYRL_COMPILE` (read now, when an update is
    built) is 1 or a backend's name; else `losses` itself (see the module doc)."""
    setting = os.environ.get("RELAYRL_COMPILE", "0")
    if setting == "0":
        return losses
    backend = "inductor" if setting == "1" else setting
    # cudagraphs captures graphs of its own, which cannot sit inside GraphedStep's capture
    valid = [b for b in torch.compiler.list_backends(exclude_tags=()) if b != "cudagraphs"]
    if backend not in valid:
        raise UserError(f"RELAYRL_COMPILE={setting!r} is not valid; valid: 0 (off), 1 (inductor), or a "
                        f"torch.compile backend other than cudagraphs: {', '.join(valid)}")
    # Every agent's losses are one code object to dynamo, recompiled for each new set of guards
    # (a config's constants, an observation kind, weighted batches or not, another agent's
    # modules on some torch versions): a process building several agents (a sweep, the tests)
    # passes dynamo's default of 8, where fullgraph=True turns the next one into an error.
    dynamo, name = torch._dynamo.config, recompile_limit_name()
    setattr(dynamo, name, max(getattr(dynamo, name), RECOMPILE_LIMIT))
    # dynamic left to torch: a value that changes between calls (a Python float such as a
    # scheduled clip range, a shorter last minibatch) gets one general graph, not one per value.
    return torch.compile(losses, fullgraph=True, backend=backend)  # type: ignore[return-value]


def recompile_limit_name() -> str:
    """dynamo's setting for compiled variants per function: `cache_size_limit` before torch 2.6."""
    return "recompile_limit" if hasattr(torch._dynamo.config, "recompile_limit") else "cache_size_limit"


class _Captured(NamedTuple):
    graph: torch.cuda.CUDAGraph
    inputs: list[Tensor | None]  # the buffers the graph reads
    outputs: dict[str, Tensor]  # the buffers it writes


class GraphedStep:
    """`step(*tensors) -> dict of tensors`, captured per input signature (see the module doc).
    The tensors must be on the CUDA device the step works on."""

    def __init__(self, step: Callable[..., dict[str, Tensor]], generators: Sequence[torch.Generator] = (),
                 max_graphs: int = 8) -> None:
        self.step = step
        self.generators = list(generators)
        self.max_graphs = max_graphs  # signatures beyond it (a policy fed every batch size) stay eager
        self._calls: dict[Signature, int] = {}
        self._graphs: dict[Signature, _Captured] = {}
        self._streams: dict[torch.device, torch.cuda.Stream] = {}

    def __call__(self, *args: Tensor | None) -> dict[str, Tensor]:
        device = next(a.device for a in args if a is not None)
        # The step's device made current: streams, capture and replay act on the current device,
        # which need not be the run's (device=cuda:1).
        with torch.cuda.device(device):
            return self._call(device, args)

    def _call(self, device: torch.device, args: tuple[Tensor | None, ...]) -> dict[str, Tensor]:
        key: Signature = tuple(None if a is None else (a.shape, a.dtype, a.device) for a in args)
        captured = self._graphs.get(key)
        if captured is None:
            if len(self._graphs) >= self.max_graphs:
                return self._eager(device, args)
            calls = self._calls.get(key, 0)
            self._calls[key] = calls + 1
            if calls < WARMUP:
                return self._eager(device, args)
            captured = self._graphs[key] = self._capture(device, args)
        for buffer, a in zip(captured.inputs, args, strict=True):
            if buffer is not None:
                assert a is not None  # the key records which args are None: a buffer stands for a tensor
                buffer.copy_(a, non_blocking=True)
        captured.graph.replay()
        return captured.outputs

    def __getstate__(self) -> dict[str, object]:
        """Pickled without its graphs and streams (device state): a copy captures its own."""
        return {"step": self.step, "generators": self.generators, "max_graphs": self.max_graphs}

    def __setstate__(self, state: dict[str, object]) -> None:
        self.__init__(**state)  # type: ignore[misc]

    def _side_stream(self, device: torch.device) -> torch.cuda.Stream:
        if device not in self._streams:
            self._streams[device] = torch.cuda.Stream(device)
        return self._streams[device]

    def _eager(self, device: torch.device, args: tuple[Tensor | None, ...]) -> dict[str, Tensor]:
        stream, current = self._side_stream(device), torch.cuda.current_stream(device)
        stream.wait_stream(current)
        with torch.cuda.stream(stream):
            out = self.step(*args)
        current.wait_stream(stream)
        return out

    def _capture(self, device: torch.device, args: tuple[Tensor | None, ...]) -> _Captured:
        """Record the step on buffers holding `args`; nothing runs until the first replay."""
        inputs = [None if a is None else a.detach().clone() for a in args]
        graph = torch.cuda.CUDAGraph()
        for gen in self.generators:
            graph.register_generator_state(gen)
        torch.cuda.synchronize(device)  # the warm-up calls' side-stream work is done before capture
        # thread_local: CUDA calls of other threads (env workers pinning frames) go on meanwhile.
        with torch.cuda.graph(graph, stream=self._side_stream(device), capture_error_mode="thread_local"):
            outputs = self.step(*inputs)
        return _Captured(graph, inputs, outputs)


class GraphedForward:
    """`net(x)` for inputs on `device`, called without gradients: replayed from a CUDA graph per
    input shape where `cuda_graphs_enabled(device)`, else launched op by op. The output is the
    graph's buffer, overwritten by the next call."""

    def __init__(self, net: Callable[[Tensor], Tensor], device: torch.device) -> None:
        self.net = net
        self.graphed = GraphedStep(self._forward) if cuda_graphs_enabled(device) else None

    def _forward(self, x: Tensor) -> dict[str, Tensor]:
        return {"out": self.net(x)}

    def __call__(self, x: Tensor) -> Tensor:
        return self.net(x) if self.graphed is None else self.graphed(x)["out"]
