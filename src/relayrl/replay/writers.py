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

from relayrl.arrays import to_numpy
from relayrl.compile import compiled
from relayrl.replay.one_step import one_env_step
from relayrl.replay.steps import StepStore
from relayrl.replay.table import Table
from relayrl.specs import Spec
from relayrl.types import Batch, Transition


class SequenceBatch(NamedTuple):
    """Sampled sequences, [N, L, ...]. Where `last` is set the row is a final observation
    and its action and reward are padding."""

    obs: torch.Tensor  # [N, L, *obs_shape]
    action: torch.Tensor  # [N, L, *act_shape]
    reward: torch.Tensor  # [N, L]
    last: torch.Tensor  # [N, L] bool
    terminated: torch.Tensor  # [N, L] bool, on last rows: the episode terminated (vs truncated)


_NEVER = np.iinfo(np.int64).max // 2  # "no final row yet"

# A slot's record: the item's flat row, its next observation's row, and (transition items)
# its n-step return and discount, copied from the rows when the item is inserted.
SLOT_RECORD = np.dtype([("row", np.int64), ("next", np.int64), ("ret", np.float32), ("disc", np.float32)])


def _np_dtype(spec: Spec) -> np.dtype:
    return torch.zeros((), dtype=spec.dtype).numpy().dtype


def _stack(xs: list[Any], keep_tensors: bool = False) -> np.ndarray:
    """Stack one field of the staged steps: one torch call for a list of tensors (~0.3 us a
    tensor) instead of a `.numpy()` per tensor (~2.5 us) and `np.stack`. `keep_tensors`:
    tensors stay tensors on their device (for a StepStore whose data lives there)."""
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
    """StepStore plumbing shared by both writers; subclasses say when windows close."""

    lookahead = 1  # rows after an item's first row that it reads

    def __init__(self, table: Table, num_envs: int, obs_spec: Spec, action_spec: Spec,
                 frame_stack: int = 1, path: str | Path | None = None, rows: int | None = None,
                 pin_memory: bool = False, chunk_length: int = 1024,
                 device: str | torch.device | None = None) -> None:
        if table.size > 0:
            raise ValueError(f"table {table.name!r} already holds items; a writer needs an empty table")
        # Enough rows that a FIFO-removed table drops items before their rows are reused;
        # final-observation rows and stacking look-back take a little more than one per item.
        per_env = -(-table.max_size // num_envs)
        self.rows = rows if rows is not None else per_env + per_env // 16 + self.lookahead + frame_stack + 2
        self.store = StepStore(num_envs, self.rows, tuple(obs_spec.shape), _np_dtype(obs_spec),
                               tuple(action_spec.shape), _np_dtype(action_spec), frame_stack, path, device)
        self.table = table
        self.num_envs = num_envs
        self.pin_memory = pin_memory
        self.slot_ref = np.zeros(table.max_size, dtype=np.int64)  # slot -> pos * B + env
        # Per slot, what a read needs before the frames: one 24-byte record, so a sampled item
        # costs one cache miss here instead of four (see SLOT_RECORD).
        self.slot_rows = np.zeros(table.max_size, dtype=SLOT_RECORD)
        self.chunk_length = chunk_length
        # Reused rows must never be inside the chunk being written.
        self._max_staged = max(1, (self.rows - frame_stack - self.lookahead - 2) // 2)
        self._stage_limit = min(self._max_staged, max(1, -(-chunk_length // num_envs)))
        self._staged: list[Transition] = []
        self._open_from = np.zeros(num_envs, dtype=np.int64)  # first position that may still become an item
        self._saved_episodes: tuple[Any, Any] = (None, None)  # see continue_episodes
        f = self.store.flat
        self._frame, self._action, self._reward, self._stamp = f("frame"), f("action"), f("reward"), f("stamp")
        self._start, self._last, self._terminated = f("start"), f("last"), f("terminated")
        self._item_key, self._ret, self._disc, self._nlen = f("item_key"), f("ret"), f("disc"), f("nlen")
        # `write` of several items in a compiled loop when numba is there (step_jit.write_records)
        self._write_records = compiled("relayrl.replay.writers_fast", "write_records")
        self._ret_disc = (np.asarray(self._ret), np.asarray(self._disc))  # plain views, as numba takes them
        table.storage = self

    # ---- the Table's storage interface ---------------------------------------------------
    def write(self, slots: np.ndarray, items: np.ndarray) -> None:
        """items: [n, 3] rows of (pos * B + env, flat row, flat next row), as `_insert` makes them."""
        if len(slots) == 1:
            slot, (ref, row, nxt) = slots[0], items[0].tolist()
            self.slot_ref[slot] = ref
            self.slot_rows[slot] = (row, nxt, self._ret[row], self._disc[row])
            return
        if self._write_records is not None:
            self._write_records(self.slot_ref, self.slot_rows, slots, items, *self._ret_disc)
            return
        self.slot_ref[slots] = items[:, 0]
        self.slot_rows[slots] = self._records(items[:, 1], items[:, 2])

    def _records(self, rows: np.ndarray, nxt: np.ndarray) -> np.ndarray:
        """Slot records for items at flat `rows` whose next observations are at `nxt`. An
        item's return and discount are final when it is inserted (its window has closed) and
        stay so until its row is reused, which evicts it first."""
        rec = np.empty(len(rows), SLOT_RECORD)
        rec["row"], rec["next"] = rows, nxt
        rec["ret"], rec["disc"] = self._ret.take(rows), self._disc.take(rows)
        return rec

    def _refs(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ref = self.slot_ref.take(slots)
        return ref % self.num_envs, ref // self.num_envs  # env, position

    def _tensor(self, x: np.ndarray | torch.Tensor) -> torch.Tensor:
        if isinstance(x, torch.Tensor):  # gathered on the store's device
            return x
        t = torch.from_numpy(x)  # gathers are fresh contiguous arrays
        if self.store.on_device:  # the small host columns join the data on its device
            return t.to(self.store.device, non_blocking=True)
        return t.pin_memory() if self.pin_memory else t

    def stale(self, slots: np.ndarray) -> np.ndarray:
        envs, pos = self._refs(slots)
        return ~self.store.valid(envs, pos, self._ahead(envs, pos))

    def _ahead(self, envs: np.ndarray, pos: np.ndarray) -> np.ndarray:
        return np.full(len(pos), self.lookahead, dtype=np.int64)

    def _next_pos(self, envs: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """Position of the row an item reads as its next observation (the row itself by default)."""
        return pos

    def state_dict(self) -> dict[str, Any]:
        self.flush()
        return {"store": self.store.state_dict(), "slot_ref": self.slot_ref.copy(),
                "open_from": self._open_from.copy()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.store.load_state_dict(state["store"])
        self.slot_ref[:] = state["slot_ref"]
        self.refresh_slot_rows()
        self._staged.clear()
        self._open_from = self.store.head.copy()  # resumed actors start new episodes...
        # ...unless their envs resume mid-episode too: then `continue_episodes()`.
        self._saved_episodes = (state.get("open_from"), state["store"].get("ep_start"))

    def refresh_slot_rows(self, slots: np.ndarray | None = None) -> None:
        """Recompute the flat rows of `slots` (default: all) from `slot_ref`."""
        ref = self.slot_ref if slots is None else self.slot_ref[slots]
        envs, pos = ref % self.num_envs, ref // self.num_envs
        at = slice(None) if slots is None else slots
        self.slot_rows[at] = self._records(envs * self.rows + pos % self.rows,
                                           envs * self.rows + self._next_pos(envs, pos) % self.rows)

    def saved_episodes_intact(self) -> bool:
        """After `load_state_dict`: whether the rows of the episodes open at the checkpoint still
        hold what it saw (memmap files reopened after the run went on may not)."""
        open_from, _ = self._saved_episodes
        if open_from is None:
            return False
        s = self.store
        for env, first in enumerate(np.asarray(open_from, dtype=np.int64).tolist()):
            pos = np.arange(max(first - s.k + 1, 0), int(s.head[env]))  # open rows and their stacking look-back
            if pos.size and not (s.stamp[env, pos % s.T] == pos + 1).all():
                return False
        return True

    def continue_episodes(self) -> None:
        """After `load_state_dict`, when the actor's envs were restored mid-episode as well:
        the next step continues the interrupted episodes (their last steps become items)."""
        open_from, ep_start = self._saved_episodes
        if open_from is None or ep_start is None:
            raise ValueError("this writer state predates episode continuation; resumed envs must start new episodes")
        self._open_from = np.asarray(open_from, dtype=np.int64).copy()
        self.store.ep_start[:] = ep_start

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

    def write_chunk(self, chunk: StepChunk) -> None:
        """Append steps stacked by `stack_steps` (possibly in another process: the replay
        server's writers take chunks from remote actors) and insert the items they close."""
        self.flush()  # steps staged here come first
        self._write(chunk.frames, chunk.actions, chunk.rewards, chunk.done, chunk.terminated, chunk.finals)

    def restart_episodes(self) -> None:
        """Forget the episodes in progress: the next steps start new ones. For an actor that
        died mid-episode and was restarted: its last steps never become items."""
        self._staged.clear()
        self._open_from = self.store.head.copy()
        self.store.ep_start[:] = self.store.head

    def _flush_one(self, t: Transition) -> bool:
        """One staged step (a 1:1 collect/train loop flushes every step): write it on a short
        path if there is one; False leaves it to the general path (always, for a store on a
        device: this path writes NumPy rows)."""
        if self.store.on_device:
            return False
        if np.count_nonzero(to_numpy(t.terminated)) or np.count_nonzero(to_numpy(t.truncated)):
            return False
        obs = to_numpy(t.obs)
        s = self.store
        self._evict(s.envs, s.head)
        self._close_newest(s.write_step(obs[:, -1] if s.k > 1 else obs, to_numpy(t.action), to_numpy(t.reward)))
        return True

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
        self._evict(envs[mask], pos[mask])
        s.write_chunk(frames, actions, rewards, done, term, finals)
        self._close_items()

    def _evict(self, envs: np.ndarray, pos: np.ndarray) -> None:
        """Drop the items that read the rows about to be reused for `pos`."""
        keys = self.store.evictable(envs, pos)
        keys = keys[keys >= 0]
        if keys.size:
            # Most are long gone (the remover took them first); the table's lock only for the rest.
            keys = keys[self.table.slot_key.take(keys % self.table.max_size) == keys]
            if keys.size:
                self.table.delete(keys)

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
        pos = self._open_from[:, None] + np.arange(w)  # [B, W]
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
        items = np.empty((len(envs), 3), dtype=np.int64)  # what `write` stores per slot
        items[:, 0] = ref
        items[:, 1] = rows = base + pos % self.rows
        items[:, 2] = base + next_pos % self.rows
        self._item_key[rows] = self.table.insert_batch(items, n=len(envs))

    def _advance(self, pos: np.ndarray, still_open: np.ndarray) -> None:
        """Next flush starts at each env's first item that may still close."""
        rows = np.arange(len(pos))
        first = np.argmax(still_open, axis=1)
        self._open_from = np.where(still_open[rows, first], pos[rows, first], self.store.head)

    def _close_items(self) -> None:
        raise NotImplementedError


class TransitionWriter(_Writer):
    """n-step transitions; `read` returns a `Batch` (weights None: the learner sets them)."""

    def __init__(self, table: Table, num_envs: int, obs_spec: Spec, action_spec: Spec, *,
                 gamma: float, n_step: int = 1, frame_stack: int = 1, path: str | Path | None = None,
                 rows: int | None = None, pin_memory: bool = False, chunk_length: int = 1024,
                 device: str | torch.device | None = None) -> None:
        if n_step < 1:
            raise ValueError(f"n_step={n_step} is not valid; it must be >= 1")
        self.n = n_step
        self.lookahead = n_step
        self.gamma = gamma
        self.powers = gamma ** np.arange(n_step + 1, dtype=np.float64)  # [n+1]
        super().__init__(table, num_envs, obs_spec, action_spec, frame_stack, path, rows, pin_memory, chunk_length,
                         device)
        # B > 1 one-step flushes in compiled loops (step_jit) when numba is there; else NumPy.
        bind = compiled("relayrl.replay.writers_fast", "bind_batched_step")
        self._batched_step = bind(self) if bind is not None and num_envs > 1 else None

    def _close_items(self) -> None:
        s, n = self.store, self.n
        envs, pos, item, end = self._window()  # [B, W]
        w = pos.shape[1]
        to_end = end - pos  # rows to the episode's final observation
        reaches_end = to_end <= n
        closed = item & (reaches_end | (pos + n < s.head[:, None]))
        length = np.where(reaches_end, to_end, n)  # [B, W]
        # n-step discounted returns over the window: rewards of rows q .. q+length-1.
        r_pos = self._open_from[:, None] + np.arange(w + n - 1)  # [B, W+n-1]
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
        i = base + q % s.T
        ret = self._reward.take(i).astype(np.float64)
        for m in range(1, n):  # left to right, as _close_items and the one-env path sum
            ret += self._reward.take(base + (q + m) % s.T) * self.powers[m]
        self._ret[i] = ret
        self._disc[i] = self.powers[n]
        self._nlen[i] = n
        self._open_from[ok] = q + 1
        self._insert(e, q, q + n)

    def _flush_one(self, t: Transition) -> bool:
        if self.num_envs == 1 and not self.store.on_device:  # (Python scalars: host rows only)
            one_env_step(self, t)
            return True
        if self._batched_step is not None and not (np.count_nonzero(to_numpy(t.terminated))
                                                   or np.count_nonzero(to_numpy(t.truncated))):
            self._batched_step(self, t)
            return True
        return super()._flush_one(t)

    def _ahead(self, envs: np.ndarray, pos: np.ndarray) -> np.ndarray:
        return self.store.nlen[envs, pos % self.rows].astype(np.int64)

    def _next_pos(self, envs: np.ndarray, pos: np.ndarray) -> np.ndarray:
        return pos + self.store.nlen[envs, pos % self.rows]

    def read(self, slots: np.ndarray) -> Batch:
        s = self.store
        rec = self.slot_rows.take(slots)  # one gather: rows, return and discount of each item
        i = rec["row"]
        if s.k == 1:
            obs, next_obs = s.gather("frame", i), s.gather("frame", rec["next"])
        else:
            envs, pos = self._refs(slots)
            start = self._start.take(i)
            obs = s.stacks(envs, pos, start)
            next_obs = s.stacks(envs, pos + self._nlen.take(i), start)
        t = self._tensor
        # ret and disc made contiguous: as views of the records they would pickle (Ray) and pin
        # the whole record array.
        return Batch(t(obs), t(s.gather("action", i)), t(np.ascontiguousarray(rec["ret"])), t(next_obs),
                     t(np.ascontiguousarray(rec["disc"])), None)


class SequenceWriter(_Writer):
    """Items of `sequence_length` rows of one episode, every `stride_length` rows."""

    def __init__(self, table: Table, num_envs: int, obs_spec: Spec, action_spec: Spec, *,
                 sequence_length: int, stride_length: int = 1, frame_stack: int = 1,
                 path: str | Path | None = None, rows: int | None = None, pin_memory: bool = False,
                 chunk_length: int = 1024, device: str | torch.device | None = None) -> None:
        if sequence_length < 1 or stride_length < 1:
            raise ValueError(f"sequence_length={sequence_length} and stride_length={stride_length} must be >= 1")
        self.L = sequence_length
        self.stride = stride_length
        self.lookahead = sequence_length - 1
        super().__init__(table, num_envs, obs_spec, action_spec, frame_stack, path, rows, pin_memory, chunk_length,
                         device)

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

    def read(self, slots: np.ndarray) -> SequenceBatch:
        s = self.store
        envs, pos = self._refs(slots)
        steps = pos[:, None] + np.arange(self.L)  # [N, L]
        rows = steps % self.rows
        e = envs[:, None]
        start = s.start[envs, pos % self.rows]
        if s.k == 1:
            obs = s.gather("frame", e * self.rows + rows)  # [N, L, *obs]
        else:
            stacks = [s.stacks(envs, steps[:, j], start) for j in range(self.L)]
            obs = torch.stack(stacks, 1) if s.on_device else np.stack(stacks, axis=1)  # type: ignore[arg-type]
        t = self._tensor
        return SequenceBatch(t(obs), t(s.gather("action", e * self.rows + rows)), t(s.reward[e, rows]),
                             t(s.last[e, rows]), t(s.terminated[e, rows]))
