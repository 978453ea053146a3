"""Writers (TF-Agents/Acme adders): cut a batched actor's stream into table items.

A writer is an actor observer: called with each batched `Transition`, it appends the steps
to its StepStore and inserts an item into its table for every window that closed. It is also
the table's storage: items are references (env, position) into the StepStore, and `read`
turns sampled references into training data. No item ever spans an episode boundary.

- `TransitionWriter(n_step)`: items (s_t, a_t, sum_i gamma^i r_{t+i}, s_{t+m}, discount),
  m = min(n, steps left in the episode); discount = gamma^m, or 0 when the episode
  terminated inside the window (bootstrap through truncation, never through termination).
- `SequenceWriter(sequence_length, stride_length)`: items of L consecutive rows of one
  episode (an episode's last row is its final observation), starting every `stride_length`
  rows from the episode start; TF-Agents' DQN tutorial uses L=2, stride 1.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from relayrl.replay.steps import StepStore
from relayrl.replay.storage import to_numpy
from relayrl.replay.table import Table
from relayrl.specs import Spec
from relayrl.types import Batch, Transition


class Sequence(NamedTuple):
    """Sampled sequences, [N, L, ...]. Where `last` is set the row is a final observation
    and its action and reward are padding."""

    obs: torch.Tensor  # [N, L, *obs_shape]
    action: torch.Tensor  # [N, L, *act_shape]
    reward: torch.Tensor  # [N, L]
    last: torch.Tensor  # [N, L] bool
    terminated: torch.Tensor  # [N, L] bool, on last rows: the episode terminated (vs truncated)


def _np_dtype(spec: Spec) -> np.dtype:
    return torch.zeros((), dtype=spec.dtype).numpy().dtype


class _Writer:
    """StepStore plumbing shared by both writers; subclasses say when windows close."""

    lookahead = 1  # rows after an item's first row that it reads

    def __init__(self, table: Table, num_envs: int, obs_spec: Spec, action_spec: Spec,
                 frame_stack: int = 1, path: str | Path | None = None, rows: int | None = None,
                 pin_memory: bool = False, chunk_length: int = 1024) -> None:
        if table.size > 0:
            raise ValueError(f"table {table.name!r} already holds items; a writer needs an empty table")
        # Enough rows that a FIFO-removed table drops items before their rows are reused;
        # final-observation rows and stacking look-back take a little more than one per item.
        per_env = -(-table.max_size // num_envs)
        self.rows = rows if rows is not None else per_env + per_env // 16 + self.lookahead + frame_stack + 2
        self.store = StepStore(num_envs, self.rows, tuple(obs_spec.shape), _np_dtype(obs_spec),
                               tuple(action_spec.shape), _np_dtype(action_spec), frame_stack, path)
        self.table = table
        self.num_envs = num_envs
        self.pin_memory = pin_memory
        self.slot_ref = np.zeros(table.max_size, dtype=np.int64)  # slot -> pos * B + env
        self.chunk_length = chunk_length
        # Reused rows must never be inside the chunk being written.
        self._max_staged = max(1, (self.rows - frame_stack - self.lookahead - 2) // 2)
        self._staged: list[tuple[np.ndarray, ...]] = []
        self._finals: list[np.ndarray] = []
        self._open_from = np.zeros(num_envs, dtype=np.int64)  # first position that may still become an item
        table.storage = self

    # ---- the Table's storage interface ---------------------------------------------------
    def write(self, slots: np.ndarray, refs: np.ndarray) -> None:
        self.slot_ref[slots] = refs

    def _refs(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ref = self.slot_ref[slots]
        return ref % self.num_envs, ref // self.num_envs  # env, position

    def _tensor(self, x: np.ndarray) -> torch.Tensor:
        t = torch.from_numpy(x)  # fancy-index gathers are fresh contiguous arrays
        return t.pin_memory() if self.pin_memory else t

    def stale(self, slots: np.ndarray) -> np.ndarray:
        envs, pos = self._refs(slots)
        return ~self.store.valid(envs, pos, self._ahead(envs, pos))

    def _ahead(self, envs: np.ndarray, pos: np.ndarray) -> np.ndarray:
        return np.full(len(pos), self.lookahead, dtype=np.int64)

    def state_dict(self) -> dict[str, Any]:
        self.flush()
        return {"store": self.store.state_dict(), "slot_ref": self.slot_ref.copy()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.store.load_state_dict(state["store"])
        self.slot_ref[:] = state["slot_ref"]
        self._staged.clear()
        self._finals.clear()
        self._open_from = self.store.head.copy()  # resumed actors start new episodes

    # ---- the observer ---------------------------------------------------------------
    def __call__(self, t: Transition) -> None:
        """Stage one batched step; items reach the table at `flush()` (every `chunk_length`
        env steps, and whenever the Actor finishes a run), like Reverb's chunked writers."""
        obs = to_numpy(t.obs)
        term = to_numpy(t.terminated)
        done = term | to_numpy(t.truncated)
        k = self.store.k
        self._staged.append((obs[:, -1] if k > 1 else obs, to_numpy(t.action), to_numpy(t.reward), done, term))
        if done.any():
            final = to_numpy(t.next_obs)[done]
            self._finals.append(final[:, -1] if k > 1 else final)
        if len(self._staged) * self.num_envs >= self.chunk_length or len(self._staged) >= self._max_staged:
            self.flush()

    def flush(self) -> None:
        """Write staged steps to the StepStore and insert every item whose window closed."""
        if not self._staged:
            return
        s = self.store
        if len(self._staged) == 1 and not self._finals:
            # One step and no episode end: the actor's per-step flush in 1:1 collect/train
            # loops. Same result as the general path below with a third of its NumPy calls.
            self._step_fast(*self._staged.pop()[:3])
            return
        frames, actions, rewards, done, term = (np.stack(x) for x in zip(*self._staged, strict=True))
        finals = np.concatenate(self._finals) if self._finals else frames[:0, 0]
        self._staged.clear()
        self._finals.clear()
        # Rows about to be reused: drop the items that read them first.
        new_rows = 1 + done.sum(axis=0)  # [B]
        j = np.arange(int(new_rows.max()))
        envs = np.broadcast_to(s.envs[:, None], (s.B, j.size))
        pos = s.head[:, None] + j  # [B, R]
        mask = j < new_rows[:, None]
        self._evict(envs[mask], pos[mask])
        s.write_chunk(frames, actions, rewards, done, term, finals)
        self._close_items()

    def _step_fast(self, frame: np.ndarray, action: np.ndarray, reward: np.ndarray) -> None:
        s = self.store
        self._evict(s.envs, s.head)
        self._close_newest(s.write_step(frame, action, reward))

    def _evict(self, envs: np.ndarray, pos: np.ndarray) -> None:
        """Drop the items that read the rows about to be reused for `pos`."""
        keys = self.store.evictable(envs, pos)
        if (keys >= 0).any():
            self.table.delete(keys[keys >= 0])

    def _close_newest(self, pos: np.ndarray) -> None:
        """After one step without episode ends: close items that this row completes."""
        self._close_items()

    def _window(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Rows from each env's first open item to its head: envs, pos [B, W], written mask, E.

        E[b, j] is the position of the first final row at or after pos[b, j] (or a large
        number when the episode is still running).
        """
        s = self.store
        w = int((s.head - self._open_from).max())
        j = np.arange(w)
        pos = self._open_from[:, None] + j  # [B, W]
        envs = np.broadcast_to(s.envs[:, None], pos.shape)
        written = pos < s.head[:, None]
        idx = envs * s.T + pos % s.T
        last = s.flat("last")[idx] & written
        never = np.iinfo(np.int64).max // 2
        final_at = np.where(last, pos, never)
        end = np.minimum.accumulate(final_at[:, ::-1], axis=1)[:, ::-1]  # [B, W]
        return envs, pos, written & ~last, end

    def _insert(self, envs: np.ndarray, pos: np.ndarray) -> None:
        if len(envs) == 0:
            return
        order = np.lexsort((envs, pos))  # oldest positions first, so FIFO removal follows time
        envs, pos = envs[order], pos[order]
        keys = self.table.insert_batch(pos * self.num_envs + envs, n=len(envs))
        self.store.flat("item_key")[envs * self.rows + pos % self.rows] = keys

    def _advance(self, pos: np.ndarray, still_open: np.ndarray) -> None:
        """Next flush starts at each env's first item that may still close."""
        first = np.argmax(still_open, axis=1)
        self._open_from = np.where(still_open.any(axis=1), pos[np.arange(len(pos)), first], self.store.head)

    def _close_items(self) -> None:
        raise NotImplementedError


class TransitionWriter(_Writer):
    """n-step transitions; `read` returns a `Batch` (weights None: the learner sets them)."""

    def __init__(self, table: Table, num_envs: int, obs_spec: Spec, action_spec: Spec, *,
                 gamma: float, n_step: int = 1, frame_stack: int = 1, path: str | Path | None = None,
                 rows: int | None = None, pin_memory: bool = False, chunk_length: int = 1024) -> None:
        if n_step < 1:
            raise ValueError(f"n_step={n_step} is not valid; it must be >= 1")
        self.n = n_step
        self.lookahead = n_step
        self.gamma = gamma
        self.powers = gamma ** np.arange(n_step + 1, dtype=np.float64)  # [n+1]
        super().__init__(table, num_envs, obs_spec, action_spec, frame_stack, path, rows, pin_memory, chunk_length)

    def _close_items(self) -> None:
        s, n = self.store, self.n
        envs, pos, item, end = self._window()  # [B, W]
        w = pos.shape[1]
        to_end = end - pos  # rows to the episode's final observation
        reaches_end = to_end <= n
        closed = item & (reaches_end | (pos + n < s.head[:, None]))
        length = np.where(reaches_end, to_end, n)  # [B, W]
        # n-step discounted returns over the window: rewards of rows q .. q+length-1.
        ahead = np.arange(w + n)
        r_pos = self._open_from[:, None] + ahead  # [B, W+n]
        rewards = s.flat("reward")[envs[:, :1] * s.T + r_pos % s.T]  # [B, W+n]
        windows = np.lib.stride_tricks.sliding_window_view(rewards, n, axis=1)[:, :w]  # [B, W, n]
        ret = (windows * self.powers[:-1] * (np.arange(n) < length[..., None])).sum(axis=2)  # [B, W]
        terminated = s.flat("terminated")[envs * s.T + np.minimum(end, pos + n) % s.T]
        disc = np.where(reaches_end & terminated, 0.0, self.powers[np.clip(length, 0, n)])
        e, p = envs[closed], pos[closed]
        i = e * s.T + p % s.T
        s.flat("ret")[i] = ret[closed]
        s.flat("disc")[i] = disc[closed]
        s.flat("nlen")[i] = length[closed]
        self._advance(pos, item & ~closed)
        self._insert(e, p)

    def _close_newest(self, pos: np.ndarray) -> None:
        # Row `pos` completes the n-step window of the item at pos - n, if that item is
        # in this episode and still open; nothing else can close without an episode end.
        s, n = self.store, self.n
        q = pos - n
        ok = q >= self._open_from
        if not ok.any():
            return
        e, q = s.envs[ok], q[ok]
        base = e * s.T
        if n == 1:
            ret = s.flat("reward")[base + q % s.T]
        else:
            ret = s.flat("reward")[base[:, None] + (q[:, None] + np.arange(n)) % s.T] @ self.powers[:-1]
        i = base + q % s.T
        s.flat("ret")[i] = ret
        s.flat("disc")[i] = self.powers[n]
        s.flat("nlen")[i] = n
        self._open_from[ok] = q + 1
        self._insert(e, q)

    def _ahead(self, envs: np.ndarray, pos: np.ndarray) -> np.ndarray:
        return self.store.nlen[envs, pos % self.rows].astype(np.int64)

    def read(self, slots: np.ndarray) -> Batch:
        s = self.store
        envs, pos = self._refs(slots)
        base = envs * s.T
        i = base + pos % s.T  # flat rows: one 1-D gather per column
        nxt = pos + s.flat("nlen")[i]
        if s.k == 1:
            obs, next_obs = s.flat("frame")[i], s.flat("frame")[base + nxt % s.T]
        else:
            start = s.flat("start")[i]
            obs, next_obs = s.stacks(envs, pos, start), s.stacks(envs, nxt, start)
        t = self._tensor
        return Batch(t(obs), t(s.flat("action")[i]), t(s.flat("ret")[i]), t(next_obs), t(s.flat("disc")[i]), None)


class SequenceWriter(_Writer):
    """Items of `sequence_length` rows of one episode, every `stride_length` rows."""

    def __init__(self, table: Table, num_envs: int, obs_spec: Spec, action_spec: Spec, *,
                 sequence_length: int, stride_length: int = 1, frame_stack: int = 1,
                 path: str | Path | None = None, rows: int | None = None, pin_memory: bool = False,
                 chunk_length: int = 1024) -> None:
        if sequence_length < 1 or stride_length < 1:
            raise ValueError(f"sequence_length={sequence_length} and stride_length={stride_length} must be >= 1")
        self.L = sequence_length
        self.stride = stride_length
        self.lookahead = sequence_length - 1
        super().__init__(table, num_envs, obs_spec, action_spec, frame_stack, path, rows, pin_memory, chunk_length)

    def _close_items(self) -> None:
        s, span = self.store, self.L - 1
        envs, pos, item, end = self._window()  # [B, W]
        start = s.flat("start")[envs * s.T + pos % s.T]
        fits = pos + span <= end  # the episode is long enough from here
        on_stride = (pos - start) % self.stride == 0
        candidate = item & fits & on_stride
        closed = candidate & (pos + span < s.head[:, None])
        self._advance(pos, candidate & ~closed)
        self._insert(envs[closed], pos[closed])

    def read(self, slots: np.ndarray) -> Sequence:
        s = self.store
        envs, pos = self._refs(slots)
        steps = pos[:, None] + np.arange(self.L)  # [N, L]
        rows = steps % self.rows
        e = envs[:, None]
        start = s.start[envs, pos % self.rows]
        if s.k == 1:
            obs = s.frame[e, rows]  # [N, L, *obs]
        else:
            obs = np.stack([s.stacks(envs, steps[:, j], start) for j in range(self.L)], axis=1)
        t = self._tensor
        return Sequence(t(obs), t(s.action[e, rows]), t(s.reward[e, rows]), t(s.last[e, rows]),
                        t(s.terminated[e, rows]))
