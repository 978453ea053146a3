"""The process-wide state a run sets and gives back: denormal flushing, threads, seeds, the
default dtype, warning filters, the thread exception hook, and the device it runs on."""

from __future__ import annotations

import contextlib
import os
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any, cast

import torch

from relayrl import atomic
from relayrl.config import Config
from relayrl.envs.make import global_rngs_kept
from relayrl.errors import UserError
from relayrl.seeding import RunSeeds


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise UserError(f"device={name!r} but CUDA is not available here; valid: cpu, auto")
    try:
        device = torch.device(name)
    except RuntimeError:  # load_policy's device is not checked as a config's is
        raise UserError(f"device={name!r} is not a device; valid: cpu, cuda, cuda:N, auto") from None
    if device.type not in ("cpu", "cuda"):  # meta, mps, xpu: torch's own error at the first call
        raise UserError(f"device={name!r}: relayrl runs on the CPU or a CUDA GPU; valid: cpu, cuda, cuda:N, auto")
    if device.type == "cuda" and device.index is not None and device.index >= (n := torch.cuda.device_count()):
        valid = f"cuda:0 to cuda:{n - 1}, cuda, cpu, auto" if n else "cpu, auto"
        raise UserError(f"device={name!r} but this machine has {n} CUDA device{'s' * (n != 1)}; valid: {valid}")
    return device


def start_process(config: Config) -> tuple[RunSeeds, torch.device]:
    """Denormal flushing, thread count, the run's seeds (torch's global generator seeded for
    network initialisation) and its device."""
    # Adam's second moments of parameters whose gradients stay ~0 (dead ReLUs) decay into the
    # denormal range, where x86 arithmetic is many times slower: flushed to zero, a small
    # network's update on a CPU takes about half the time. Set before torch starts its thread
    # pool, whose threads inherit the setting.
    torch.set_flush_denormal(True)
    if config.train.torch_threads > 0:
        torch.set_num_threads(config.train.torch_threads)
    seeds = RunSeeds(config.seed)
    torch.manual_seed(seeds.base("torch"))
    return seeds, resolve_device(config.device)


@contextlib.contextmanager
def caller_state_kept() -> Iterator[None]:
    """The caller's torch thread count, denormal flushing, default dtype and torch, NumPy and
    Python global generators as they were before the run (`start_process` sets them for it, a
    resume loads the checkpoint's), so that a notebook's own code after `relayrl.train` runs as
    it did before."""
    threads = torch.get_num_threads()
    cuda = torch.cuda.get_rng_state_all() if torch.cuda.is_initialized() else None  # manual_seed seeds these too
    flushing = torch.tensor([1e-39]).item() == 0.0  # torch has no getter: a float32 denormal reads 0 when flushed
    try:
        with global_rngs_kept(), float32_default(), numpy_warnings_left_out(), writer_thread_quiet():
            yield
    finally:
        torch.set_num_threads(threads)
        torch.set_flush_denormal(flushing)
        if cuda is not None:
            torch.cuda.set_rng_state_all(cuda)


def _folder_gone(error: BaseException | None) -> bool:
    """Whether `error` is a FileNotFoundError for a file whose folder is gone (the run directory
    deleted under the run, which the run's next write says in one line)."""
    if not isinstance(error, FileNotFoundError) or not error.filename:
        return False
    return not Path(os.fsdecode(error.filename)).parent.exists()


@contextlib.contextmanager
def numpy_warnings_left_out() -> Iterator[None]:
    """NumPy's overflow and invalid-value warnings from relayrl's own code left out: an
    observation beyond float32 becomes inf in relayrl's write (and NaN in the policy's matmul),
    which the finite watch names in one line; the warnings, each with its source line, would only
    precede it. One filter entry, taken out again after (not the whole list restored, which would
    drop a filter a library imported during the run installs)."""
    warnings.filterwarnings("ignore", "(overflow|invalid value) encountered", RuntimeWarning, r"relayrl\.")
    ours = warnings.filters[0]
    try:
        yield
    finally:
        with contextlib.suppress(ValueError):  # gone already: warnings.resetwarnings() during the run
            cast(list, warnings.filters).remove(ours)  # typeshed declares a Sequence; it is the list warn() reads


@contextlib.contextmanager
def writer_thread_quiet() -> Iterator[None]:
    """TensorBoard's writer thread stopped by a full disk or a folder made read-only prints no
    traceback of its own: its error reaches the run at its next write, which says it in one line
    (`run_to_end`, `atomic.replacing`). Other threads' errors go to the hook there was, which is
    put back after."""
    import threading

    before = threading.excepthook

    def hook(args: Any) -> None:
        if type(args.thread).__name__ == "_AsyncWriterThread" and (atomic.unwritable(args.exc_value) is not None
                                                                   or _folder_gone(args.exc_value)):
            return
        before(args)

    threading.excepthook = hook
    try:
        yield
    finally:
        if threading.excepthook is hook:  # else replaced during the run: that one stays
            threading.excepthook = before


@contextlib.contextmanager
def float32_default() -> Iterator[None]:
    """torch's default dtype float32 inside, the caller's after: relayrl's networks and the
    tensors it makes are float32 also where a notebook set torch.set_default_dtype(torch.float64)
    (its float64 weights met float32 observations in torch's own dtype error)."""
    before = torch.get_default_dtype()
    torch.set_default_dtype(torch.float32)
    try:
        yield
    finally:
        torch.set_default_dtype(before)
