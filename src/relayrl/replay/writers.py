"""Writers (TF-Agents/Acme adders): cut a batched actor's stream into table items.

A writer is an actor observer: called with each batched `Transition`, it stages the step;
at a flush it appends the staged steps to its StepStore and inserts an item into its table
for every window that closed. Items are references into the StepStore: the writer gives the
table a `StepStorage` over its store (`Table.set_storage`), which turns sampled references
into training data. Before rows are reused, the writer deletes the items that read them
(`Table.delete`, which ignores items already gone). No item ever spans an episode boundary.

- `TransitionWriter(n_step)`: items (s_t, a_t, sum_i gamma^i r_{t+i}, s_{t+m}, discount),
  m = min(n, steps left in the episode); discount = gamma^m, or 0 when the episode
  terminated inside the window (bootstrap through truncation, never through termination).
- `SequenceWriter(sequence_length, stride_length)`: items of L consecutive rows of one
  episode (an episode's last row is its final observation), starting every `stride_length`
  rows from the episode start; TF-Agents' DQN tutorial uses L=2, stride 1.

A flush takes the general path (`_write`, any number of steps and episode ends), or, for
one staged step without episode ends in a TransitionWriter, its compiled twin
(`writers_fast.OneStep`, with `fast=True` and numba there): the step of a 1:1 collect/train
loop, which flushes after every batched step.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from relayrl.arrays import to_numpy
from relayrl.compile import numba_available
from relayrl.replay.step_storage import SequenceBatch, SequenceStorage, StepStorage, TransitionStorage
from relayrl.replay.steps import StepStore
from relayrl.replay.table import Table
from relayrl.specs import Spec, numpy_dtype
from relayrl.types import Transition

__all__ = ["SequenceBatch", "SequenceWriter", "StepChunk", "TransitionWriter", "stack_steps"]

_NEVER = np.iinfo(np.int64).max // 2  # "no final row yet"


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


class StepChunk(NamedTuple):
    """C batched steps as plain arrays, what a writer appends at a flush: small enough to
    ship between processes (one newest frame per step when observations are stacked)."""

    frames: np.ndarray  # [C, B, *frame]
    actions: np.ndarray  # [C, B, *act_shape]
    rewards: np.ndarray  # [C, B]
    done: np.ndarray  # [C, B] bool: terminated or truncated
    terminated: np.ndarray  # [C, B] bool
    finals: np.ndarray  # [D, *frame]: final observations where `done`, in (step, env) order

    @property
    def env_steps(self) -> int:
        return int(self.done.size)


def stack_steps(staged: list[Transition], frame_stack: int = 1, keep_tensors: bool = False) -> StepChunk:
    """Stack batched Transitions into a StepChunk (frames, actions and final observations as
    tensors where they came as tensors, with `keep_tensors`)."""
    k = frame_stack
    frames = _stack([t.obs[:, -1] for t in staged] if k > 1 else [t.obs for t in staged], keep_tensors)
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
    return StepChunk(frames, actions, rewards, done, term, final[:, -1] if finals and k > 1 else final)


class _Writer:
    """Staging, eviction and inserts shared by both writers; subclasses say when windows close."""

    lookahead = 1  # rows after an item's first row that it reads

    def __init__(self, table: Table, num_envs: int, obs_spec: Spec, action_spec: Spec,
                 frame_stack: int = 1, path: str | Path | None = None, rows: int | None = None,
                 chunk_length: int = 1024, device: str | torch.device | None = None) -> None:
        if table.size > 0:
            raise ValueError(f"table {table.name!r} already holds items; a writer needs an empty table")
        # Enough rows that a FIFO-removed table drops items before their rows are reused;
        # final-observation rows and stacking look-back take a little more than one per item.
        per_env = -(-table.max_size // num_envs)
        self.rows = rows if rows is not None else per_env + per_env // 16 + self.lookahead + frame_stack + 2
        self.store = StepStore(num_envs, self.rows, tuple(obs_spec.shape), numpy_dtype(obs_spec),
                               tuple(action_spec.shape), numpy_dtype(action_spec), frame_stack, path, device)
        self.table = table
        self.num_envs = num_envs
        self.chunk_length = chunk_length
        # Reused rows must never be inside the chunk being written.
        self.max_staged = max(1, (self.rows - frame_stack - self.lookahead - 2) // 2)
        self._stage_limit = min(self.max_staged, max(1, -(-chunk_length // num_envs)))
        self._staged: list[Transition] = []
        f = self.store.flat
        self._reward, self._start, self._last, self._terminated = f("reward"), f("start"), f("last"), f("terminated")
        self._ret, self._disc, self._nlen = f("ret"), f("disc"), f("nlen")

    def _use_storage(self, storage: StepStorage) -> None:
        self.storage = storage
        self.open_from = storage.open_from  # updated in place only: the storage saves it
        self.table.set_storage(storage)

    # ---- checkpoints (the storage's state is in the table's) -------------------------------
    def saved_episodes_intact(self) -> bool:
        """After the table loaded a checkpoint: whether the rows of the episodes open at the
        checkpoint still hold what it saw (memmap files reopened after the run went on may not)."""
        return self.storage.saved_episodes_intact()

    def continue_episodes(self) -> None:
        """After the table loaded a checkpoint, when the actor's envs were restored mid-episode
        as well: the next step continues the interrupted episodes (their last steps become items)."""
        self._staged.clear()
        open_from, ep_start = self.storage.saved_episodes
        if open_from is None or ep_start is None:
            raise ValueError("this writer state predates episode continuation; resumed envs must start new episodes")
        self.open_from[:] = np.asarray(open_from, dtype=np.int64)
        self.store.ep_start[:] = ep_start

    def restart_episodes(self) -> None:
        """Forget the episodes in progress: the next steps start new ones. For an actor that
        died mid-episode and was restarted: its last steps never become items."""
        self._staged.clear()
        self.open_from[:] = self.store.head
        self.store.ep_start[:] = self.store.head

    # ---- the observer ---------------------------------------------------------------
    def __call__(self, t: Transition) -> None:
        """Stage one batched step; items reach the table at `flush()` (every `chunk_length`
        env steps, and whenever the Actor finishes a run), like Reverb's chunked writers.
        The step's tensors are held, not copied, until then: an env must not write into
        tensors it has already returned."""
        self._staged.append(t)
        if len(self._staged) >= self._stage_limit:
            self.flush()

    def flush(self) -> None:
        """Write staged steps to the StepStore and insert every item whose window closed."""
        staged = self._staged
        if not staged:
            return
        if len(staged) == 1 and self._flush_one(staged[0]):
            staged.clear()
            return
        chunk = stack_steps(staged, self.store.k, keep_tensors=self.store.on_device)
        staged.clear()
        self.write_chunk(chunk)

    def _flush_one(self, t: Transition) -> bool:
        """Write one staged step on a compiled path if there is one; False: the general path."""
        return False

    def write_chunk(self, chunk: StepChunk) -> None:
        """Append steps stacked by `stack_steps` (possibly in another process: the replay
        server's writers take chunks from remote actors) and insert the items they close."""
        self.flush()  # steps staged here come first
        self._write(chunk.frames, chunk.actions, chunk.rewards, chunk.done, chunk.terminated, chunk.finals)

    def _write(self, frames: np.ndarray | torch.Tensor, actions: np.ndarray | torch.Tensor, rewards: np.ndarray,
               done: np.ndarray, term: np.ndarray, finals: np.ndarray | torch.Tensor) -> None:
        """The general path: C steps [C, B, ...] and the final observations where `done`."""
        s = self.store
        # Rows about to be reused: drop the items that read them first.
        new_rows = done.shape[0] + done.sum(axis=0)  # [B]: a row per step, one more per episode end
        j = np.arange(int(new_rows.max()))
        envs = np.repeat(s.envs, j.size).reshape(s.B, j.size)
        pos = s.head[:, None] + j  # [B, R]
        mask = j < new_rows[:, None]
        keys = s.evictable(envs[mask], pos[mask])
        keys = keys[keys >= 0]
        if keys.size:
            self.table.delete(keys)  # most are long gone (the remover took them first)
        s.write_chunk(frames, actions, rewards, done, term, finals)
        self._close_items()

    def _window(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Rows from each env's first open item to its head: envs, pos [B, W], written mask, E.

        E[b, j] is the position of the first final row at or after pos[b, j] (or a large
        number when the episode is still running).
        """
        s = self.store
        w = int((s.head - self.open_from).max())
        pos = self.open_from[:, None] + np.arange(w)  # [B, W]
        envs = np.repeat(s.envs, w).reshape(pos.shape)
        written = pos < s.head[:, None]
        last = self._last[envs * s.T + pos % s.T] & written
        final_at = np.where(last, pos, _NEVER)
        end = np.minimum.accumulate(final_at[:, ::-1], axis=1)[:, ::-1]  # [B, W]
        return envs, pos, written & ~last, end

    def _insert(self, envs: np.ndarray, pos: np.ndarray, next_pos: np.ndarray) -> None:
        """Insert items starting at (envs, pos) whose next observation is at next_pos."""
        if len(envs) == 0:
            return
        ref = pos * self.num_envs + envs
        if self.num_envs > 1 and len(envs) > 1:
            # Oldest positions first, so FIFO removal follows time. Refs are unique; a stable
            # sort is the cheap one here (the input is one sorted run per env).
            order = np.argsort(ref, kind="stable")
            envs, pos, next_pos, ref = envs.take(order), pos.take(order), next_pos.take(order), ref.take(order)
        base = envs * self.rows
        items = np.empty((len(envs), 3), dtype=np.int64)  # what `StepStorage.write` stores per slot
        items[:, 0] = ref
        items[:, 1] = base + pos % self.rows
        items[:, 2] = base + next_pos % self.rows
        self.table.insert_batch(items, n=len(envs))  # (the storage notes each item's key at its row)

    def _advance(self, pos: np.ndarray, still_open: np.ndarray) -> None:
        """Next flush starts at each env's first item that may still close."""
        rows = np.arange(len(pos))
        first = np.argmax(still_open, axis=1)
        self.open_from[:] = np.where(still_open[rows, first], pos[rows, first], self.store.head)

    def _close_items(self) -> None:
        raise NotImplementedError


class TransitionWriter(_Writer):
    """n-step transitions; the table's samples are `Batch`es (weights None: the learner sets them).

    `fast`: one-step flushes without episode ends in compiled loops (`writers_fast`) when
    numba is there; False (or no numba, or RELAYRL_NUMBA=0): always the general NumPy path."""

    def __init__(self, table: Table, num_envs: int, obs_spec: Spec, action_spec: Spec, *,
                 gamma: float, n_step: int = 1, frame_stack: int = 1, path: str | Path | None = None,
                 rows: int | None = None, pin_memory: bool = False, chunk_length: int = 1024,
                 device: str | torch.device | None = None, fast: bool = True) -> None:
        if n_step < 1:
            raise ValueError(f"n_step={n_step} is not valid; it must be >= 1")
        self.n = n_step
        self.lookahead = n_step
        self.gamma = gamma
        self.powers = gamma ** np.arange(n_step + 1, dtype=np.float64)  # [n+1]
        super().__init__(table, num_envs, obs_spec, action_spec, frame_stack, path, rows, chunk_length, device)
        self._use_storage(TransitionStorage(self.store, table.max_size, pin_memory, fast))
        self._one_step: Any = None  # the general path
        if fast and numba_available():
            from relayrl.replay.writers_fast import OneStep
            self._one_step = OneStep(self)

    def _flush_one(self, t: Transition) -> bool:
        return self._one_step is not None and self._one_step(t)

    def _close_items(self) -> None:
        s, n = self.store, self.n
        envs, pos, item, end = self._window()  # [B, W]
        w = pos.shape[1]
        to_end = end - pos  # rows to the episode's final observation
        reaches_end = to_end <= n
        closed = item & (reaches_end | (pos + n < s.head[:, None]))
        length = np.where(reaches_end, to_end, n)  # [B, W]
        # n-step discounted returns over the window: rewards of rows q .. q+length-1.
        r_pos = self.open_from[:, None] + np.arange(w + n - 1)  # [B, W+n-1]
        rewards = self._reward[envs[:, :1] * s.T + r_pos % s.T]  # [B, W+n-1]
        ret = rewards[:, :w].astype(np.float64)  # m = 0: every item has length >= 1
        for m in range(1, n):
            ret += rewards[:, m:m + w] * self.powers[m] * (m < length)
        terminated = self._terminated[envs * s.T + np.minimum(end, pos + n) % s.T]
        disc = np.where(reaches_end & terminated, 0.0, self.powers.take(length))  # length is in [0, n]
        e, p, m = envs[closed], pos[closed], length[closed]
        i = e * s.T + p % s.T
        self._ret[i] = ret[closed]
        self._disc[i] = disc[closed]
        self._nlen[i] = m
        self._advance(pos, item & ~closed)
        self._insert(e, p, p + m)


class SequenceWriter(_Writer):
    """Items of `sequence_length` rows of one episode, every `stride_length` rows; the
    table's samples are `SequenceBatch`es."""

    def __init__(self, table: Table, num_envs: int, obs_spec: Spec, action_spec: Spec, *,
                 sequence_length: int, stride_length: int = 1, frame_stack: int = 1,
                 path: str | Path | None = None, rows: int | None = None, pin_memory: bool = False,
                 chunk_length: int = 1024, device: str | torch.device | None = None) -> None:
        if sequence_length < 1 or stride_length < 1:
            raise ValueError(f"sequence_length={sequence_length} and stride_length={stride_length} must be >= 1")
        self.L = sequence_length
        self.stride = stride_length
        self.lookahead = sequence_length - 1
        super().__init__(table, num_envs, obs_spec, action_spec, frame_stack, path, rows, chunk_length, device)
        self._use_storage(SequenceStorage(self.store, table.max_size, sequence_length, pin_memory))

    def _close_items(self) -> None:
        s, span = self.store, self.L - 1
        envs, pos, item, end = self._window()  # [B, W]
        start = self._start[envs * s.T + pos % s.T]
        fits = pos + span <= end  # the episode is long enough from here
        on_stride = (pos - start) % self.stride == 0
        candidate = item & fits & on_stride
        closed = candidate & (pos + span < s.head[:, None])
        self._advance(pos, candidate & ~closed)
        self._insert(envs[closed], pos[closed], pos[closed])
