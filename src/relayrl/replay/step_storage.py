"""StepStorage: a Table's storage of steps and of the items that are windows of them.

A table whose items are windows of steps (n-step transitions, sequences) owns a StepStorage,
and through it the steps (a StepStore: RAM, memmap or device columns, stacked pixel frames
stored once per frame). Writers hand steps to the table (`Table.append_steps`); the table asks
its storage which live items the new rows overwrite (`evictions`), deletes them, has the
storage append the rows (`append`, which returns the items the new steps close) and inserts
those. So every deletion is the table's decision, and nothing flows back to a writer.

An item, as the table inserts it, is a row of three int64s: (position * num_envs + env, flat
row, flat row of its next observation). Per slot the storage keeps that reference and a
record of what a read needs before the frames (`SLOT_RECORD`), so a sampled item costs one
gather there. Each item's key is noted at its first row (`item_key`): the item to evict when
that row is reused. No item ever spans an episode boundary.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from relayrl.compile import numba_available
from relayrl.replay.steps import StepChunk, StepStore
from relayrl.replay.storage import Storage
from relayrl.specs import Spec, numpy_dtype
from relayrl.types import Batch

# A slot's record: the item's flat row, its next observation's row, and (transition items)
# its n-step return and discount, copied from the rows when the item is inserted: one
# 24-byte record per sampled item instead of four scattered reads.
SLOT_RECORD = np.dtype([("row", np.int64), ("next", np.int64), ("ret", np.float32), ("disc", np.float32)])

_NEVER = np.iinfo(np.int64).max // 2  # "no final row yet"


class SequenceBatch(NamedTuple):
    """Sampled sequences, [N, L, ...]. Where `last` is set the row is a final observation
    and its action and reward are padding."""

    obs: torch.Tensor  # [N, L, *obs_shape]
    action: torch.Tensor  # [N, L, *act_shape]
    reward: torch.Tensor  # [N, L]
    last: torch.Tensor  # [N, L] bool
    terminated: torch.Tensor  # [N, L] bool, on last rows: the episode terminated (vs truncated)


def ring_rows(capacity: int, num_envs: int, lookahead: int, frame_stack: int = 1) -> int:
    """Rows of each env's ring for `capacity` items: final-observation rows and stacking
    look-back take a little more than one row per item."""
    per_env = -(-capacity // num_envs)
    return per_env + per_env // 16 + lookahead + frame_stack + 2


class StepStorage(Storage):
    """Steps of `num_envs` envs and the slot map of the items over them (see the module
    docstring). `lookahead`: rows after an item's first row that it reads. `rows`: each env's
    ring length (default: enough that a FIFO-removed table of `capacity` drops items before
    their rows are reused). `fast`: write several items' records in a compiled loop when
    numba is there."""

    def __init__(self, capacity: int, num_envs: int, obs_spec: Spec, action_spec: Spec, *, lookahead: int,
                 frame_stack: int = 1, path: str | Path | None = None, rows: int | None = None,
                 device: str | torch.device | None = None, fast: bool = True) -> None:
        rows = rows if rows is not None else ring_rows(capacity, num_envs, lookahead, frame_stack)
        self.store = StepStore(num_envs, rows, tuple(obs_spec.shape), numpy_dtype(obs_spec),
                               tuple(action_spec.shape), numpy_dtype(action_spec), frame_stack, path, device)
        self.capacity, self.num_envs, self.rows = capacity, num_envs, rows
        # Batched steps one `append` may take: reused rows must never be inside the chunk being written.
        self.max_append_steps = max(1, (rows - frame_stack - lookahead - 2) // 2)
        self.slot_ref = np.zeros(capacity, dtype=np.int64)  # slot -> pos * num_envs + env
        self.slot_rows = np.zeros(capacity, dtype=SLOT_RECORD)
        self.open_from = np.zeros(num_envs, dtype=np.int64)  # per env: first position that may still become an item
        self.saved_episodes: tuple[Any, Any] = (None, None)  # (open_from, ep_start) of a loaded checkpoint
        # `evictions` and `append` of one batched step without episode ends, in compiled loops
        # (step_storage_fast.OneStep); None: the general path takes every step.
        self.one_step: Any = None
        f = self.store.flat
        self._reward, self._start, self._last, self._terminated = f("reward"), f("start"), f("last"), f("terminated")
        self._ret, self._disc, self._nlen, self._item_key = f("ret"), f("disc"), f("nlen"), f("item_key")
        self.bind(np.full(capacity, -1, dtype=np.int64))  # until a table hands over its key map
        self._write_records: Any = None  # the NumPy path
        if fast and numba_available():
            from relayrl.replay.step_storage_fast import write_records
            self._write_records = write_records

    def bind(self, slot_key: np.ndarray) -> None:
        self.slot_key = slot_key
        # What `write_records` reads and writes besides the slot map, as plain ndarray views.
        self._columns = (np.asarray(self._ret), np.asarray(self._disc), slot_key, np.asarray(self._item_key))

    # ---- appending steps (the table calls these) ------------------------------------------
    @property
    def appending(self) -> StepStorage:
        """The storage that takes appended steps: this one (a StorageGroup names one of its own)."""
        return self

    def evictions(self, done: np.ndarray) -> np.ndarray:
        """Keys of the items whose rows appending steps with episode ends `done` [C, B] overwrites
        (most are long gone, taken by the remover first; `Table.delete` skips those)."""
        s = self.store
        new_rows = done.shape[0] + done.sum(axis=0)  # [B]: a row per step, one more per episode end
        j = np.arange(int(new_rows.max()))
        envs = np.repeat(s.envs, j.size).reshape(s.num_envs, j.size)
        pos = s.head[:, None] + j  # [B, R]
        mask = j < new_rows[:, None]
        keys = s.evictable(envs[mask], pos[mask])
        return keys[keys >= 0]

    def append(self, chunk: StepChunk) -> np.ndarray:
        """Append a chunk's rows (after the table deleted its `evictions`); returns the items it
        closes, [n, 3] as `write` takes them, oldest first."""
        self.store.write_chunk(chunk)
        return self._close_items()

    # ---- episodes across checkpoints and restarts -------------------------------------------
    def saved_episodes_intact(self) -> bool:
        """After `load_state_dict`: whether the rows of the episodes open at the checkpoint still
        hold what it saw (memmap files reopened after the run went on may not)."""
        open_from, _ = self.saved_episodes
        if open_from is None:
            return False
        s = self.store
        for env, first in enumerate(np.asarray(open_from, dtype=np.int64).tolist()):
            pos = np.arange(max(first - s.frame_stack + 1, 0), int(s.head[env]))  # open rows, stacking look-back
            if pos.size and not (s.stamp[env, pos % s.rows] == pos + 1).all():
                return False
        return True

    def continue_episodes(self) -> None:
        """After `load_state_dict`, when the actor's envs were restored mid-episode as well: the
        next steps continue the interrupted episodes (their last steps become items)."""
        open_from, ep_start = self.saved_episodes
        if open_from is None or ep_start is None:
            raise ValueError("this replay state predates episode continuation; resumed envs must start new episodes")
        self.open_from[:] = np.asarray(open_from, dtype=np.int64)
        self.store.ep_start[:] = ep_start

    def restart_episodes(self) -> None:
        """Forget the episodes in progress: the next steps start new ones (for an actor that
        died mid-episode and was restarted: its last steps never become items)."""
        self.open_from[:] = self.store.head
        self.store.ep_start[:] = self.store.head

    # ---- the Table's storage interface ---------------------------------------------------
    def write(self, slots: np.ndarray, items: np.ndarray) -> None:
        """items: [n, 3] rows of (pos * num_envs + env, flat row, flat next row)."""
        if len(slots) == 1:
            slot, (ref, row, nxt) = slots[0], items[0].tolist()
            self.slot_ref[slot] = ref
            self.slot_rows[slot] = (row, nxt, self._ret[row], self._disc[row])
            self._item_key[row] = self.slot_key[slot]
            return
        if self._write_records is not None:
            self._write_records(self.slot_ref, self.slot_rows, slots, items, *self._columns)
            return
        self.slot_ref[slots] = items[:, 0]
        self.slot_rows[slots] = self._records(items[:, 1], items[:, 2])
        self._item_key[items[:, 1]] = self.slot_key.take(slots)

    def read(self, slots: np.ndarray) -> Any:
        raise NotImplementedError

    def stale(self, slots: np.ndarray) -> np.ndarray:
        envs, pos = self.refs(slots)
        return ~self.store.valid(envs, pos, self.ahead(envs, pos))

    def state_dict(self) -> dict[str, Any]:
        live = np.flatnonzero(self.slot_key >= 0)
        used = int(live[-1]) + 1 if live.size else 0  # a table fills its slots from 0 up
        return {"store": self.store.state_dict(), "slot_ref": self.slot_ref[:used].copy(),
                "open_from": self.open_from.copy()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.store.load_state_dict(state["store"])
        saved = np.asarray(state["slot_ref"])  # the slots up to the last live one (older checkpoints: all)
        self.slot_ref[:] = 0
        self.slot_ref[:saved.size] = saved
        self.refresh_slot_rows()
        self.open_from[:] = self.store.head  # resumed actors start new episodes, unless
        self.saved_episodes = (state.get("open_from"), state["store"].get("ep_start"))  # they continue them

    # ---- for readers ---------------------------------------------------------------------
    def refs(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Env and position of the items in `slots`."""
        ref = self.slot_ref.take(slots)
        return ref % self.num_envs, ref // self.num_envs

    def ahead(self, envs: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """Rows after an item's first row that it reads."""
        raise NotImplementedError

    def next_pos(self, envs: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """Position of the row an item reads as its next observation (the row itself by default)."""
        return pos

    def refresh_slot_rows(self, slots: np.ndarray | None = None) -> None:
        """Recompute the records of `slots` (default: all) from `slot_ref`."""
        ref = self.slot_ref if slots is None else self.slot_ref[slots]
        envs, pos = ref % self.num_envs, ref // self.num_envs
        at = slice(None) if slots is None else slots
        self.slot_rows[at] = self._records(envs * self.rows + pos % self.rows,
                                           envs * self.rows + self.next_pos(envs, pos) % self.rows)

    def _records(self, rows: np.ndarray, nxt: np.ndarray) -> np.ndarray:
        """Records of items at flat `rows` whose next observations are at `nxt`. An item's
        return and discount are final when it is inserted (its window has closed) and stay so
        until its row is reused, which evicts it first."""
        rec = np.empty(len(rows), SLOT_RECORD)
        rec["row"], rec["next"] = rows, nxt
        rec["ret"], rec["disc"] = self._ret.take(rows), self._disc.take(rows)
        return rec

    def _tensor(self, x: np.ndarray | torch.Tensor) -> torch.Tensor:
        if isinstance(x, torch.Tensor):  # gathered on the store's device
            return x
        t = torch.from_numpy(x)  # gathers are fresh contiguous arrays
        if self.store.on_device:  # the small host columns join the data on its device
            return t.to(self.store.device, non_blocking=True)
        return t

    # ---- closing items (subclasses say which windows are items) ---------------------------
    def _close_items(self) -> np.ndarray:
        raise NotImplementedError

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
        last = self._last[envs * s.rows + pos % s.rows] & written
        final_at = np.where(last, pos, _NEVER)
        end = np.minimum.accumulate(final_at[:, ::-1], axis=1)[:, ::-1]  # [B, W]
        return envs, pos, written & ~last, end

    def _items(self, envs: np.ndarray, pos: np.ndarray, next_pos: np.ndarray) -> np.ndarray:
        """Items starting at (envs, pos) whose next observation is at next_pos: [n, 3], oldest first."""
        ref = pos * self.num_envs + envs
        if self.num_envs > 1 and len(envs) > 1:
            # Oldest positions first, so FIFO removal follows time. Refs are unique; a stable
            # sort is the cheap one here (the input is one sorted run per env).
            order = np.argsort(ref, kind="stable")
            envs, pos, next_pos, ref = envs.take(order), pos.take(order), next_pos.take(order), ref.take(order)
        base = envs * self.rows
        items = np.empty((len(envs), 3), dtype=np.int64)
        items[:, 0] = ref
        items[:, 1] = base + pos % self.rows
        items[:, 2] = base + next_pos % self.rows
        return items

    def _advance(self, pos: np.ndarray, still_open: np.ndarray) -> None:
        """The next append starts at each env's first item that may still close."""
        rows = np.arange(len(pos))
        first = np.argmax(still_open, axis=1)
        self.open_from[:] = np.where(still_open[rows, first], pos[rows, first], self.store.head)


class TransitionStorage(StepStorage):
    """Items (s_t, a_t, sum_i gamma^i r_{t+i}, s_{t+m}, discount), m = min(n_step, steps left in
    the episode); discount = gamma^m, or 0 when the episode terminated inside the window
    (bootstrap through truncation, never through termination). `read` returns a `Batch`
    (weights None: the learner sets them). `fast`: a `one_step` path when numba is there."""

    def __init__(self, capacity: int, num_envs: int, obs_spec: Spec, action_spec: Spec, *, gamma: float,
                 n_step: int = 1, frame_stack: int = 1, path: str | Path | None = None, rows: int | None = None,
                 device: str | torch.device | None = None, fast: bool = True) -> None:
        if n_step < 1:
            raise ValueError(f"n_step={n_step} is not valid; it must be >= 1")
        super().__init__(capacity, num_envs, obs_spec, action_spec, lookahead=n_step, frame_stack=frame_stack,
                         path=path, rows=rows, device=device, fast=fast)
        self.n_step = n_step
        self.gamma = gamma
        self.powers = gamma ** np.arange(n_step + 1, dtype=np.float64)  # [n+1]
        if fast and numba_available():
            from relayrl.replay.step_storage_fast import OneStep
            self.one_step = OneStep(self)

    def _close_items(self) -> np.ndarray:
        s, n = self.store, self.n_step
        envs, pos, item, end = self._window()  # [B, W]
        w = pos.shape[1]
        to_end = end - pos  # rows to the episode's final observation
        reaches_end = to_end <= n
        closed = item & (reaches_end | (pos + n < s.head[:, None]))
        length = np.where(reaches_end, to_end, n)  # [B, W]
        # n-step discounted returns over the window: rewards of rows q .. q+length-1.
        r_pos = self.open_from[:, None] + np.arange(w + n - 1)  # [B, W+n-1]
        rewards = self._reward[envs[:, :1] * s.rows + r_pos % s.rows]  # [B, W+n-1]
        ret = rewards[:, :w].astype(np.float64)  # m = 0: every item has length >= 1
        for m in range(1, n):
            ret += rewards[:, m:m + w] * self.powers[m] * (m < length)
        terminated = self._terminated[envs * s.rows + np.minimum(end, pos + n) % s.rows]
        disc = np.where(reaches_end & terminated, 0.0, self.powers.take(length))  # length is in [0, n]
        e, p, m = envs[closed], pos[closed], length[closed]
        i = e * s.rows + p % s.rows
        self._ret[i] = ret[closed]
        self._disc[i] = disc[closed]
        self._nlen[i] = m
        self._advance(pos, item & ~closed)
        return self._items(e, p, p + m)

    def ahead(self, envs: np.ndarray, pos: np.ndarray) -> np.ndarray:
        return self.store.nlen[envs, pos % self.rows].astype(np.int64)

    def next_pos(self, envs: np.ndarray, pos: np.ndarray) -> np.ndarray:
        return pos + self.store.nlen[envs, pos % self.rows]

    def read(self, slots: np.ndarray) -> Batch:
        s = self.store
        rec = self.slot_rows.take(slots)  # one gather: rows, return and discount of each item
        i = rec["row"]
        if s.frame_stack == 1:
            obs, next_obs = s.gather("frame", i), s.gather("frame", rec["next"])
        else:
            envs, pos = self.refs(slots)
            start = self._start.take(i)
            obs = s.stacks(envs, pos, start)
            next_obs = s.stacks(envs, pos + self._nlen.take(i), start)
        t = self._tensor
        # ret and disc made contiguous: as views of the records they would pickle (Ray) and pin
        # the whole record array.
        return Batch(t(obs), t(s.gather("action", i)), t(np.ascontiguousarray(rec["ret"])), t(next_obs),
                     t(np.ascontiguousarray(rec["disc"])), None)


class SequenceStorage(StepStorage):
    """Items of `sequence_length` rows of one episode (an episode's last row is its final
    observation), starting every `stride_length` rows from the episode start; `read` returns a
    `SequenceBatch`. TF-Agents' DQN tutorial uses sequence_length=2, stride 1."""

    def __init__(self, capacity: int, num_envs: int, obs_spec: Spec, action_spec: Spec, *, sequence_length: int,
                 stride_length: int = 1, frame_stack: int = 1, path: str | Path | None = None,
                 rows: int | None = None, device: str | torch.device | None = None) -> None:
        if sequence_length < 1 or stride_length < 1:
            raise ValueError(f"sequence_length={sequence_length} and stride_length={stride_length} must be >= 1")
        super().__init__(capacity, num_envs, obs_spec, action_spec, lookahead=sequence_length - 1,
                         frame_stack=frame_stack, path=path, rows=rows, device=device)
        self.sequence_length = sequence_length
        self.stride_length = stride_length

    def _close_items(self) -> np.ndarray:
        s, span = self.store, self.sequence_length - 1
        envs, pos, item, end = self._window()  # [B, W]
        start = self._start[envs * s.rows + pos % s.rows]
        fits = pos + span <= end  # the episode is long enough from here
        on_stride = (pos - start) % self.stride_length == 0
        candidate = item & fits & on_stride
        closed = candidate & (pos + span < s.head[:, None])
        self._advance(pos, candidate & ~closed)
        return self._items(envs[closed], pos[closed], pos[closed])

    def ahead(self, envs: np.ndarray, pos: np.ndarray) -> np.ndarray:
        return np.full(len(pos), self.sequence_length - 1, dtype=np.int64)

    def read(self, slots: np.ndarray) -> SequenceBatch:
        s, rows, length = self.store, self.rows, self.sequence_length
        envs, pos = self.refs(slots)
        steps = pos[:, None] + np.arange(length)  # [N, L]
        row = steps % rows
        e = envs[:, None]
        start = s.start[envs, pos % rows]
        if s.frame_stack == 1:
            obs = s.gather("frame", e * rows + row)  # [N, L, *obs]
        else:
            stacks = [s.stacks(envs, steps[:, j], start) for j in range(length)]
            obs = torch.stack(stacks, 1) if s.on_device else np.stack(stacks, axis=1)  # type: ignore[arg-type]
        t = self._tensor
        return SequenceBatch(t(obs), t(s.gather("action", e * rows + row)), t(s.reward[e, row]), t(s.last[e, row]),
                             t(s.terminated[e, row]))
