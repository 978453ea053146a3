"""StepStore: the steps of `num_envs` parallel episodes, each observation stored once.

Env b writes its steps into its own ring of `rows` rows. A row holds the observation an action
was taken from, the action and the reward; when an episode ends, one more row holds its
final observation (no action). A transition's next observation is simply a later row of
the same ring, so observations are never stored twice, and n-step windows and sequences
are gathers. With `frame_stack=k`, observations are [k, *frame] stacks and a row stores
only the newest frame; stacks are rebuilt at read time from the previous k-1 rows of the
same episode, repeating its first frame before the start (Gymnasium's
`FrameStackObservation(padding_type="reset")`).

Positions are absolute (they only grow); row = position % rows. A row's `stamp` is position+1,
so a reader can tell a row that was overwritten, or written after a checkpoint, from the
one it expects.

With `device`, the frames and actions (the bulk of the data) are torch tensors on that
device, so an env, a policy and a learner on one GPU never copy them through the host; the
bookkeeping columns stay NumPy arrays on the host, where indexing them from Python is cheap.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from relayrl.arrays import to_numpy, torch_dtype
from relayrl.replay.storage import Columns, Signature

DATA = ("frame", "action")  # the columns that live on `device` when the store has one


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


class StepStore:
    def __init__(self, num_envs: int, rows: int, obs_shape: tuple[int, ...], obs_dtype: np.dtype,
                 action_shape: tuple[int, ...], action_dtype: np.dtype, frame_stack: int = 1,
                 path: str | Path | None = None, device: str | torch.device | None = None) -> None:
        if frame_stack < 1:
            raise ValueError(f"frame_stack={frame_stack} is not valid; it must be >= 1")
        if frame_stack > 1 and (len(obs_shape) < 2 or obs_shape[0] != frame_stack):
            raise ValueError(f"frame_stack={frame_stack} needs observations shaped [{frame_stack}, ...], "
                             f"got {list(obs_shape)}")
        self.num_envs = num_envs
        self.rows = rows  # per env: the length of its ring
        self.frame_stack = frame_stack
        frame_shape = obs_shape[1:] if frame_stack > 1 else obs_shape
        self.obs_shape, self.action_shape = tuple(obs_shape), tuple(action_shape)  # one env's, as written
        sig: Signature = {
            "frame": (frame_shape, obs_dtype), "action": (action_shape, action_dtype),
            "reward": ((), np.float32), "stamp": ((), np.int64), "start": ((), np.int64),
            "last": ((), np.bool_), "terminated": ((), np.bool_), "item_key": ((), np.int64),
            # Filled by the transition writer when an item's n-step window closes.
            "ret": ((), np.float32), "disc": ((), np.float32), "nlen": ((), np.int16),
        }
        self.device = torch.device(device) if device is not None else None
        if self.device is not None and path is not None:
            raise ValueError("memmap storage lives on disk; its frames cannot also live on a torch device")
        self.data: dict[str, torch.Tensor] = {}
        if self.device is not None:
            for name in DATA:
                shape, dtype = sig.pop(name)
                self.data[name] = torch.zeros((num_envs, rows, *shape), dtype=torch_dtype(dtype), device=self.device)
        self.cols = Columns(sig, (num_envs, rows), path=path)
        c = {**self.cols.arrays, **self.data}
        self.frame, self.action, self.reward, self.stamp = c["frame"], c["action"], c["reward"], c["stamp"]
        self.start, self.last, self.terminated = c["start"], c["last"], c["terminated"]
        self.ret, self.nlen = c["ret"], c["nlen"]
        self._flat = {k: a.reshape((num_envs * rows,) + tuple(a.shape[2:])) for k, a in c.items()}
        # Columns with a row shape (frames, vector actions) as one opaque element per row:
        # assigning rows by index is then a 1-D scatter, several times cheaper than a 2-D one.
        self._row_views = {k: _row_view(a) for k, a in self._flat.items()
                      if k not in self.data and a.ndim > 1 and a[0].nbytes > 0}
        self.head = np.zeros(num_envs, dtype=np.int64)  # next position per env
        self.ep_start = np.zeros(num_envs, dtype=np.int64)  # first position of the running episode
        self.envs = np.arange(num_envs)

    @property
    def on_device(self) -> bool:
        return self.device is not None

    def nbytes(self) -> int:
        return self.cols.nbytes() + sum(t.nbytes for t in self.data.values())

    def evictable(self, envs: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """Keys of items that writing `pos` would corrupt (-1 where none).

        An item at p reads rows p-k+1 .. p+n; writing q overwrites q-T, which the item at
        q-T+k-1 is the newest to need. Older ones were evicted by earlier writes.
        """
        p = pos - self.rows + self.frame_stack - 1
        i = envs * self.rows + p % self.rows
        written = (self._flat["stamp"].take(i) == p + 1) & (p >= 0)  # p < 0: the ring's first lap
        return np.where(written, self._flat["item_key"].take(i), -1)

    def flat(self, name: str) -> np.ndarray:
        """A column as [B * T, ...] (a view), so (env, row) is one flat index."""
        return self._flat[name]

    def write_chunk(self, chunk: StepChunk) -> None:
        frames, actions, rewards, done, terminated, final_frames = chunk
        c, b = done.shape
        any_done = np.count_nonzero(done) > 0
        if any_done:
            new_rows = 1 + done.astype(np.int64)  # [C, B]
            pos = self.head + np.cumsum(new_rows, axis=0) - new_rows  # [C, B] position of each step's row
            # The episode each step belongs to starts after the latest earlier final row.
            after_final = np.where(done, pos + 2, -1)  # [C, B]
            start = np.maximum.accumulate(np.vstack([self.ep_start[None], after_final[:-1]]), axis=0)  # [C, B]
        else:  # the same, without episode ends: one row per step
            pos = self.head + np.arange(c)[:, None]
            start = np.repeat(self.ep_start[None], c, axis=0)
        i = ((self.envs * self.rows) + pos % self.rows).reshape(-1)  # [C*B] flat rows
        self._write_rows(i, pos.reshape(-1), start.reshape(-1), frames.reshape((c * b,) + frames.shape[2:]),
                         actions.reshape((c * b,) + actions.shape[2:]), rewards.reshape(-1))
        if any_done:
            ce, be = np.nonzero(done)  # (step, env) order, as final_frames
            fp = pos[ce, be] + 1
            j = be * self.rows + fp % self.rows
            self._write_rows(j, fp, start[ce, be], final_frames, None, 0.0, last=True, terminated=terminated[ce, be])
            self.ep_start = np.maximum(self.ep_start, after_final.max(axis=0))
            self.head = self.head + new_rows.sum(axis=0)
        else:
            self.head = self.head + c

    def write_data(self, i: np.ndarray, frames: np.ndarray | torch.Tensor, actions: np.ndarray | torch.Tensor) -> None:
        """Frames and actions of flat rows `i` alone (the compiled one-step append writes the rest)."""
        self._put("frame", i, frames)
        self._put("action", i, actions)

    def _write_rows(self, i: np.ndarray, pos: np.ndarray, start: np.ndarray, frames: np.ndarray,
                    actions: np.ndarray | None, rewards: np.ndarray | float, last: bool = False,
                    terminated: np.ndarray | bool = False) -> None:
        """Fill flat rows `i` (positions `pos`); a final-observation row has no action."""
        f = self._flat
        self._put("frame", i, frames)
        if actions is not None:
            self._put("action", i, actions)
        f["reward"][i] = rewards
        f["stamp"][i] = pos + 1
        f["start"][i] = start
        f["last"][i] = last
        f["terminated"][i] = terminated
        f["item_key"][i] = -1

    def _put(self, name: str, i: np.ndarray, values: np.ndarray | torch.Tensor) -> None:
        """flat(name)[i] = values, through the row view where the column has one."""
        col, rows = self._flat[name], self._row_views.get(name)
        if len(i) == 0:
            return
        if name in self.data:
            v = torch.as_tensor(values).to(col.device, col.dtype)  # no-op for the env's device tensors
            col.index_copy_(0, self.index(i), v.expand((len(i), *col.shape[1:])))
        elif rows is None:
            col[i] = values
        else:
            shape = (len(i),) + col.shape[1:]
            if np.shape(values) != shape:
                values = np.broadcast_to(values, shape)
            rows[i] = np.ascontiguousarray(values, dtype=col.dtype).reshape(len(i), -1).view(rows.dtype).reshape(-1)

    def index(self, i: np.ndarray) -> torch.Tensor:
        """Flat row indices as a tensor on the data's device."""
        return torch.from_numpy(np.ascontiguousarray(i, dtype=np.int64)).to(self.device, non_blocking=True)

    def gather(self, name: str, i: np.ndarray) -> np.ndarray | torch.Tensor:
        """Rows `i` ([N] or [N, L] flat indices) of a column: [*i.shape, ...]."""
        col = self._flat[name]
        if name in self.data:
            return col.index_select(0, self.index(i.reshape(-1))).reshape(*i.shape, *col.shape[1:])
        return col.take(i, axis=0)  # `take` on flat columns: cheaper than fancy indexing

    def stacks(self, envs: np.ndarray, pos: np.ndarray, start: np.ndarray) -> np.ndarray | torch.Tensor:
        """Stacked observations at `pos`: [N, k, *frame], rebuilt from single frames (k > 1)."""
        back = np.arange(self.frame_stack - 1, -1, -1)  # [k] oldest first
        idx = np.maximum(pos[:, None] - back, start[:, None]) % self.rows  # [N, k]
        return self.gather("frame", envs[:, None] * self.rows + idx)  # [N, k, *frame]

    def valid(self, envs: np.ndarray, pos: np.ndarray, ahead: np.ndarray) -> np.ndarray:
        """Whether rows pos-k+1 (or the episode start) .. pos+ahead still hold what an item read."""
        r = pos % self.rows
        ok = self.stamp[envs, r] == pos + 1
        start = self.start[envs, r]
        span = int(ahead.max(initial=0)) + self.frame_stack
        for j in range(-(self.frame_stack - 1), span):
            p = pos + j
            need = (p >= start) & (p <= pos + ahead) & ok
            ok &= ~need | (self.stamp[envs, p % self.rows] == p + 1)
        return ok

    def state_dict(self) -> dict[str, Any]:
        used = min(int(self.head.max(initial=0)), self.rows)  # ring positions written so far
        state: dict[str, Any] = {"columns": self.cols.state_dict(used), "head": self.head.copy(),
                                 "ep_start": self.ep_start.copy()}
        if self.data:  # as host arrays, so a checkpoint loads on a machine without the device
            state["columns"].setdefault("arrays", {}).update({k: t[:, :used].cpu().numpy()
                                                              for k, t in self.data.items()})
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        columns = dict(state["columns"])
        if self.data:  # a checkpoint from a store with or without a device loads in either
            arrays = dict(columns["arrays"])
            for name, t in self.data.items():
                saved = torch.as_tensor(to_numpy(arrays.pop(name)))
                t[:, :saved.shape[1]].copy_(saved)
            columns["arrays"] = arrays
        self.cols.load_state_dict(columns)
        self.head[:] = state["head"]
        # By default a resumed actor starts fresh episodes, so the steps of the interrupted
        # ones are never joined to new ones; a writer whose env state was restored too
        # continues them (`StepStorage.continue_episodes`).
        self.ep_start[:] = self.head


def _row_view(a: np.ndarray) -> np.ndarray:
    """[N, ...] (C-contiguous) as [N] elements of one opaque row each (a view)."""
    row = int(np.prod(a.shape[1:])) * a.itemsize
    return a.reshape(a.shape[0], -1).view(np.dtype((np.void, row))).reshape(-1)
