"""Writers (TF-Agents/Acme adders): cut a batched actor's stream into a table's items.

A writer is an actor observer: called with each batched `Transition`, it stages the step;
at a flush it hands the staged steps to its table (`Table.append_steps`, or `append_step` for
the one step a 1:1 collect/train loop flushes). The table owns the steps and the items over
them: the writer gives it a step storage when it is built (see step_storage) and keeps none.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, cast

import numpy as np
import torch

from relayrl.arrays import to_numpy
from relayrl.core import Observer
from relayrl.replay.step_storage import SequenceBatch, SequenceStorage, StepStorage, TransitionStorage
from relayrl.replay.steps import StepChunk
from relayrl.replay.table import Table
from relayrl.specs import Spec
from relayrl.types import Transition

__all__ = ["SequenceBatch", "SequenceWriter", "StepChunk", "TransitionWriter", "stack_steps"]


def _stack(xs: list[Any], keep_tensors: bool = False) -> np.ndarray:
    """Stack one field of the staged steps: one torch call for a list of tensors, much cheaper
    than a `.numpy()` per tensor and `np.stack`. `keep_tensors`: tensors stay tensors on their
    device (for a StepStore whose data lives there)."""
    if isinstance(xs[0], torch.Tensor):
        try:
            stacked = torch.stack(xs)
            return stacked if keep_tensors else to_numpy(stacked)  # type: ignore[return-value]
        except TypeError:  # some steps came as NumPy arrays
            pass
    return np.stack([to_numpy(x) for x in xs])


def stack_steps(staged: list[Transition], frame_stack: int = 1, keep_tensors: bool = False) -> StepChunk:
    """Stack batched Transitions into a StepChunk (frames, actions and final observations as
    tensors where they came as tensors, with `keep_tensors`)."""
    frames = _stack([t.obs[:, -1] for t in staged] if frame_stack > 1 else [t.obs for t in staged], keep_tensors)
    actions, rewards = _stack([t.action for t in staged], keep_tensors), _stack([t.reward for t in staged])
    term = _stack([t.terminated for t in staged])
    done = term | _stack([t.truncated for t in staged])
    ended = np.flatnonzero(done.any(axis=1)).tolist()
    if isinstance(frames, torch.Tensor):
        finals = [staged[c].next_obs[torch.from_numpy(done[c]).to(frames.device)] for c in ended]
        final = torch.cat(finals) if finals else frames[:0, 0]
    else:
        finals = [to_numpy(staged[c].next_obs)[done[c]] for c in ended]
        final = np.concatenate(finals) if finals else frames[:0, 0]
    return StepChunk(frames, actions, rewards, done, term, final[:, -1] if finals and frame_stack > 1 else final)


class _Writer(Observer):
    """Staging shared by both writers; the table and its step storage do the rest."""

    def __init__(self, table: Table, storage: StepStorage, chunk_length: int) -> None:
        if table.size > 0:
            raise ValueError(f"table {table.name!r} already holds items; a writer needs an empty table")
        self.frame_stack = storage.store.frame_stack
        self.max_staged = storage.max_append_steps  # batched steps one `Table.append_steps` may take
        self._stage_limit = min(self.max_staged, max(1, -(-chunk_length // storage.num_envs)))
        self._keep_tensors = storage.store.on_device  # staged tensors stay on the store's device
        self._one_step = storage.one_step is not None
        self._staged: list[Transition] = []
        # a step's rows, checked as staged: the one-step path copies a row's columns unchecked
        self._obs_row = (storage.num_envs, *storage.store.obs_shape)
        self._action_size = storage.num_envs * int(np.prod(storage.store.action_shape))
        table.set_storage(storage)  # the table owns the steps from here on
        self.table = table

    def _steps(self) -> StepStorage:
        # The storage handed over in __init__; in a WriterGroup the group's active one, which
        # the group sets to this writer's before every call it makes on it.
        return cast(StepStorage, self.table.storage.appending)

    # ---- episodes across checkpoints and restarts: the step storage's (see there) -----------
    def saved_episodes_intact(self) -> bool:
        return self._steps().saved_episodes_intact()

    def continue_episodes(self) -> None:
        self._staged.clear()
        self._steps().continue_episodes()

    def restart_episodes(self) -> None:
        self._staged.clear()
        self._steps().restart_episodes()

    # ---- the observer ---------------------------------------------------------------
    def __call__(self, t: Transition) -> None:
        """Stage one batched step; items reach the table at `flush()` (every `chunk_length`
        env steps, and whenever the Actor ends a collect call), like Reverb's chunked writers.
        The step's tensors are held, not copied, until then: an env must not write into
        tensors it has already returned."""
        actions = t.action.numel() if isinstance(t.action, torch.Tensor) else np.size(t.action)
        if t.obs.shape != self._obs_row or actions != self._action_size:
            raise ValueError(f"a step of observations {list(t.obs.shape)} and actions {list(np.shape(t.action))}, but "
                             f"this writer takes observations {list(self._obs_row)} and {self._action_size} action "
                             "values (num_envs rows of its specs' shapes)")
        self._staged.append(t)
        if len(self._staged) >= self._stage_limit:
            self.flush()

    def flush(self) -> None:
        """Hand the staged steps to the table, which inserts every item whose window closed."""
        staged = self._staged
        if not staged:
            return
        if len(staged) == 1 and self._one_step and self._append_one(staged[0]):
            staged.clear()
            return
        chunk = stack_steps(staged, self.frame_stack, keep_tensors=self._keep_tensors)
        staged.clear()
        self.table.append_steps(chunk)

    def _append_one(self, t: Transition) -> bool:
        """One step without episode ends on the table's one-step path; False: an episode ended."""
        if np.count_nonzero(to_numpy(t.terminated)) or np.count_nonzero(to_numpy(t.truncated)):
            return False
        return self.table.append_step(t.obs[:, -1] if self.frame_stack > 1 else t.obs, t.action, t.reward)

    def write_chunk(self, chunk: StepChunk) -> None:
        """Append steps stacked by `stack_steps` (possibly in another process: the replay
        server's writers take chunks from remote actors) and insert the items they close."""
        self.flush()  # steps staged here come first
        self.table.append_steps(chunk)


class TransitionWriter(_Writer):
    """n-step transitions (see `TransitionStorage`); the table's samples are `Batch`es.

    `fast`: one-step flushes without episode ends in compiled loops when numba is there;
    False (or no numba, or RELAYRL_NUMBA=0): always the general NumPy path."""

    def __init__(self, table: Table, num_envs: int, obs_spec: Spec, action_spec: Spec, *,
                 gamma: float, n_step: int = 1, frame_stack: int = 1, path: str | Path | None = None,
                 rows: int | None = None, chunk_length: int = 1024, device: str | torch.device | None = None,
                 fast: bool = True) -> None:
        storage = TransitionStorage(table.max_size, num_envs, obs_spec, action_spec, gamma=gamma, n_step=n_step,
                                    frame_stack=frame_stack, path=path, rows=rows, device=device, fast=fast)
        super().__init__(table, storage, chunk_length)


class SequenceWriter(_Writer):
    """Items of `sequence_length` rows of one episode, every `stride_length` rows (see
    `SequenceStorage`); the table's samples are `SequenceBatch`es."""

    def __init__(self, table: Table, num_envs: int, obs_spec: Spec, action_spec: Spec, *,
                 sequence_length: int, stride_length: int = 1, frame_stack: int = 1,
                 path: str | Path | None = None, rows: int | None = None, chunk_length: int = 1024,
                 device: str | torch.device | None = None) -> None:
        storage = SequenceStorage(table.max_size, num_envs, obs_spec, action_spec, sequence_length=sequence_length,
                                  stride_length=stride_length, frame_stack=frame_stack, path=path, rows=rows,
                                  device=device)
        super().__init__(table, storage, chunk_length)
