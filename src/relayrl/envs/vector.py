"""Gymnasium envs stepped in worker processes, as one batched env (`env.vectorization = "async"`).

The copies are shared out in contiguous slices: the first to the main process, one to each of
`env.num_workers` worker processes (0, the default: one per CPU core beside the main
process's). Every slice is stepped by the in-process `GymBatchEnv`, so autoreset, seeding
(copy i gets seed + i wherever it lives), time limits and episode infos are the in-process
code's, and transitions are identical to `sync`'s.

The pipes carry pickled (command, seq, argument) one way and (status, seq, value) the other,
each reply after the bytes `worker.MAGIC`. Ctrl-C (a notebook's interrupt) may stop a call anywhere;
the next call sends a "sync" first and drops replies whose seq is not its own, so it neither
waits for a reply that was already read nor takes an interrupted call's reply for its own. An
interrupt that cuts a big message (a get_state or set_state of large envs) in two makes the env
say it is broken at its next call, rather than hang (`AsyncGymBatchEnv._fill`).

Envs that draw from the global RNGs (`np.random`, `random`, torch's) instead of their own
`self.np_random` cannot give sync's numbers: every worker seeds its own (`worker.global_rng_seed`).

Why this shape: more processes than cores never speeds up CPU-bound envs, and one process per
copy (Gymnasium's `AsyncVectorEnv`) pays a pipe round trip per copy per step, which for light
envs costs more than the step itself. The main process steps its own slice while the workers
step theirs, so it does not sleep through the step and pay a wake-up to read the results.
Workers read actions from and write results into shared memory; the pipes carry one small
command per worker per step and, when an episode ends, its info values.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import pickle
import struct
import sys
import time
from multiprocessing.connection import Connection
from typing import Any

import cloudpickle
import numpy as np
import torch

from relayrl.envs.gym import BatchEnvBase, GymBatchEnv
from relayrl.envs.pixels import frame_stack_of
from relayrl.envs.resolve import EnvFn
from relayrl.envs.worker import (
    LENGTH,
    MAGIC,
    MAIN_ENDS,
    ONE_WRITE,
    SharedLayout,
    global_rng_seed,
    serve,
    shared_views,
    worker_failure,
    worker_slices,
)
from relayrl.errors import UserError
from relayrl.specs import numpy_dtype
from relayrl.types import EpisodeInfo, StepOutput

# How long a worker may take to make its env copies and answer (see `_await_start`): generous, as
# some simulators take many seconds to start; without a limit a worker that never answers would
# make the run wait without end.
WORKER_START_S = 300.0
# fork on Linux: workers start in milliseconds and inherit what they need. Elsewhere spawn: macOS
# has fork, but its system libraries are not safe to use after one.
START_METHOD = "fork" if sys.platform.startswith("linux") else "spawn"

class AsyncGymBatchEnv(BatchEnvBase):
    """`len(env_fns)` copies: the first slice stepped in this process, the others by
    `num_workers` worker processes (0: one per core beside this one)."""

    def __init__(self, env_fns: list[EnvFn], time_limit_terminates: bool = False, num_workers: int = 0) -> None:
        self._conns: list[Connection] = []
        self._procs: list[Any] = []
        self._inbox: list[bytearray] = []  # bytes read from each pipe, not yet taken as replies
        self._seq = 0  # the last command's (0: the workers' "ok" once their envs are made)
        self._unsettled = True  # a command's replies are not all read yet (see _resync)
        self._broken: str | None = None  # why the pipes cannot be used again
        self._closed = False
        self.slices = worker_slices(len(env_fns), num_workers)
        self._k = self.slices[0][1]  # copies [0, k) are this process's
        self._local = GymBatchEnv(env_fns[:self._k], time_limit_terminates)
        try:  # from here on a failure closes what was made: this process's envs, started workers
            first = self._local.envs[0]
            self._init_specs(len(env_fns), first.observation_space, first.action_space, time_limit_terminates,
                             frame_stack_of(first))
            # The env's own action dtype: a worker's copies get the values sync hands its copies,
            # whatever the dtype of the actions given (an int or float64 Box included).
            space_dtype = getattr(first.action_space, "dtype", None)
            act_dtype = np.dtype(space_dtype if space_dtype is not None else numpy_dtype(self.action_spec))
            ctx = mp.get_context("spawn") if START_METHOD == "spawn" else mp.get_context("fork")
            # actions in the env's own shape, as `_actions` hands them on
            act_shape = tuple(self.action_spec.shape) if self._env_action_shape is None else self._env_action_shape
            b, obs = self.num_envs, ((self.num_envs, *self.observation_spec.shape), np.dtype(self._obs_dtype))
            # actions in; next_obs, reset obs, reward, terminated, truncated out
            layout: SharedLayout = {"action": ((b, *act_shape), act_dtype), "next_obs": obs, "obs": obs,
                                     "reward": ((b,), np.dtype(np.float32)), "terminated": ((b,), np.dtype(np.bool_)),
                                     "truncated": ((b,), np.dtype(np.bool_))}
            raw = {k: ctx.RawArray("b", max(1, int(np.prod(shape)) * dtype.itemsize))
                   for k, (shape, dtype) in layout.items()}
            self._arrays = shared_views(raw, layout)
            try:  # before any pipe or process is made
                pickled = [cloudpickle.dumps(env_fns[lo:hi]) for lo, hi in self.slices[1:]]
            except Exception as e:  # what a factory holds: a lock, an open file, a simulator's handle
                raise UserError(f"env.vectorization='async' sends the env factory to its worker processes "
                                f"pickled, and it cannot be pickled ({type(e).__name__}: {e}): make what it "
                                "holds inside it, or use env.vectorization='sync'") from None
            for (lo, hi), fns in zip(self.slices[1:], pickled, strict=True):
                parent, child = ctx.Pipe()
                MAIN_ENDS.add(parent)  # before the fork: the worker closes its copy of it too
                seed = global_rng_seed(lo)
                proc = ctx.Process(target=serve, name=f"relayrl-env-{lo}-{hi}", daemon=True,
                                   args=(child, fns, lo, hi, raw, layout, time_limit_terminates, seed))
                proc.start()
                child.close()
                self._conns.append(parent)
                self._procs.append(proc)
                self._inbox.append(bytearray())
            self._await_start()
            self._gather(0)
        except BaseException:
            self.close()
            raise

    @property
    def info_keys(self) -> tuple[str, ...]:
        return self._info_keys

    @info_keys.setter
    def info_keys(self, keys: tuple[str, ...]) -> None:  # make_env sets it after construction
        self._info_keys = tuple(keys)
        self._local.info_keys = self._info_keys
        if self._conns:
            self._command("info_keys", self._info_keys)

    def _await_start(self) -> None:
        """Wait for every worker's first reply (its "ok" or its failure) for at most WORKER_START_S,
        so a worker that never answers is an error, not a wait without end."""
        deadline = time.monotonic() + WORKER_START_S
        for w, conn in enumerate(self._conns):
            if not conn.poll(max(0.0, deadline - time.monotonic())):
                raise RuntimeError(
                    f"env worker {w} ({self._copies(w)}) did not answer within {WORKER_START_S:.0f} s of "
                    "its start: making its env copies hangs or takes longer than that; a worker forked from a "
                    "process with other threads (a notebook's, Ray's) can also deadlock before it starts. "
                    "env.vectorization='sync' steps the copies without worker processes")

    def _read(self, w: int, seq: int) -> tuple[str, Any]:
        """Worker w's reply to command `seq`; replies to earlier, interrupted calls are dropped."""
        while True:
            frame = self._take(w)
            if frame is None:
                self._fill(w)
                continue
            status, got, value = pickle.loads(frame)
            if got == seq:
                return status, value

    def _take(self, w: int) -> bytearray | None:
        """The next whole reply in worker w's inbox, taken out of it; None until one is whole."""
        box = self._inbox[w]
        if len(box) < 8:
            return None
        (size,) = LENGTH.unpack_from(box)  # -1: a size over 2 GiB follows
        start = 4
        if size == -1:
            if len(box) < 16:
                return None
            (size,), start = struct.unpack_from("!Q", box, 4), 12
        if not box.startswith(MAGIC, start):
            raise RuntimeError(self._break(f"the pipe from env worker {w} lost bytes to an interrupted call"))
        if len(box) < start + size:
            return None
        frame = box[start + 4:start + size]  # a copy
        del box[:start + size]  # one step: an interrupt leaves the reply in the inbox or takes it whole
        return frame

    def _fill(self, w: int) -> None:
        """Waits for worker w's next bytes and adds them to its inbox.

        Ctrl-C (a notebook's interrupt) may land anywhere here. In the wait it reads nothing (a
        read interrupted by a signal returns no bytes). Between the read and the inbox it drops
        what was read. With an empty inbox that is whole replies (each is one write smaller than
        a read), which only the interrupted call waited for and later calls tell apart by seq, or
        the head of a big one (a get_state), and then the next bytes fail the `MAGIC` check.
        With part of a big reply in the inbox the rest may have been dropped, so the env is marked
        broken. Either way it says so at its next call, instead of hanging or unpickling garbage.
        """
        conn = self._conns[w]
        if sys.platform == "win32":  # no file descriptor to read: whole messages, through the Connection
            conn.poll(None)
            try:
                data = conn.recv_bytes()
            except EOFError:
                data = b""
            except BaseException:  # it may stop between a message's length and its bytes
                self._break(f"a call to the env was interrupted while it read from env worker {w}")
                raise
            chunk = LENGTH.pack(len(data)) + data if data else b""
        else:
            try:
                chunk = os.read(conn.fileno(), 1 << 16)  # (a read allocates its size: 1 MiB costs an mmap a step)
            except ConnectionResetError:
                chunk = b""
            except BaseException:
                if self._inbox[w]:
                    self._break(f"a call to the env was interrupted while it read a large reply from env worker {w}")
                raise
        if not chunk:
            raise RuntimeError(self._died(w))
        self._inbox[w].extend(chunk)

    def _break(self, what: str) -> str:
        """Marks the pipes unusable because `what` happened: every later call says so."""
        self._broken = f"{what}; close() this env and make a new one"
        return self._broken

    def _died(self, w: int) -> str:
        """Marks the pipes unusable because worker w died; the message."""
        self._procs[w].join(timeout=2)  # reaped, so its exit code is known
        self._broken = f"env worker {w} ({self._copies(w)}) died (exit code {self._procs[w].exitcode})"
        if self._seq == 0 and START_METHOD == "spawn":  # before its first answer
            # A spawned worker runs the main script's top level again first: one that starts the
            # run unguarded starts another run there, which multiprocessing refuses, above.
            self._broken += (" before it made its env copies: a worker process started by spawn (macOS, Windows) "
                             "runs the main script's top level again, so a script must start the run under "
                             "`if __name__ == \"__main__\":`; its own error is printed above")
        return self._broken

    def _copies(self, w: int) -> str:
        """Worker w's env copies, by their index in the whole batch."""
        lo, hi = self.slices[w + 1]
        return f"copy {lo}" if hi - lo == 1 else f"copies {lo}..{hi - 1}"

    def _gather(self, seq: int, drop_errors: bool = False) -> list[Any]:
        """Every worker's reply to command `seq`, in order; a worker's failure is raised here
        (unless `drop_errors`: after a failure in this process, which is the one raised)."""
        replies: list[Any] = []
        failure: Exception | None = None
        for w in range(len(self._conns)):
            status, value = self._read(w, seq)
            if status == "user_error":
                failure = failure or UserError(value)
            elif status == "error":
                failure = failure or worker_failure(w, *value)
            replies.append(value)
        self._unsettled = False
        if failure is not None and not drop_errors:  # raised once every reply is read
            raise failure
        return replies

    def _ready(self) -> None:
        """Before a command: the env is usable and every worker is done with the last one."""
        if self._broken is not None:
            raise RuntimeError(self._broken)
        if self._closed:
            raise RuntimeError("this env is closed")
        if self._unsettled:
            self._resync()

    def _resync(self) -> None:
        """After an interrupted call (Ctrl-C during a step): a "sync" to every worker, answered
        after whatever it was still doing, so no worker still reads the shared actions or writes
        results when the next command starts (the interrupted call's replies are dropped by seq)."""
        self._gather(self._send("sync"), drop_errors=True)

    def _settle(self, seq: int) -> None:
        """After this process's copies failed: the workers' replies to `seq` read, their errors
        dropped (the local failure is the one raised; a worker killed by the same SIGTERM to the
        process group would otherwise replace it, and the env says so at its next call)."""
        with contextlib.suppress(Exception):
            self._gather(seq, drop_errors=True)

    def _send(self, cmd: str, arg: Any = None, per_worker: list[Any] | None = None) -> int:
        """Sends a command to every worker; its seq, for `_gather`."""
        self._seq += 1
        self._unsettled = True
        for w, conn in enumerate(self._conns):
            data = pickle.dumps((cmd, self._seq, arg if per_worker is None else per_worker[w]))
            try:
                conn.send_bytes(data)
            except (BrokenPipeError, ConnectionResetError):
                raise RuntimeError(self._died(w)) from None
            except BaseException:
                # A small message goes out in one write, whole or not at all; a large one (a
                # set_state of big envs) in several, and the worker may be left with part of it.
                if len(data) > ONE_WRITE:
                    self._break(f"a call to the env was interrupted while it wrote to env worker {w}")
                raise
        return self._seq

    def _command(self, cmd: str, arg: Any = None, per_worker: list[Any] | None = None) -> list[Any]:
        self._ready()
        return self._gather(self._send(cmd, arg, per_worker))

    def get_state(self) -> list[bytes] | None:
        """As `GymBatchEnv.get_state`: this process's copies, then each worker's, pickled there."""
        parts = [self._local.get_state(), *self._command("get_state")]
        return None if any(p is None for p in parts) else [s for p in parts for s in p]

    def state_problem(self) -> str | None:
        """As `GymBatchEnv.state_problem`: this process's copies first, then each worker's."""
        return self._local.state_problem() or next((why for why in self._command("state_problem") if why), None)

    def set_state(self, states: list[bytes]) -> None:
        self._local.set_state(states[:self._k])
        self._command("set_state", per_worker=[states[lo:hi] for lo, hi in self.slices[1:]])

    def reset(self, seed: int | None = None) -> torch.Tensor:
        self._ready()
        seq = self._send("reset", seed)
        try:
            local = self._local.reset(seed)
        except Exception:
            self._settle(seq)
            raise
        self._gather(seq)
        obs = self._arrays["obs"].copy()
        obs[:self._k] = local.numpy()  # (the in-process rows were checked by their own reset)
        self._check_observations(obs[self._k:], "reset")
        return torch.from_numpy(obs)

    def step(self, action: torch.Tensor) -> StepOutput:
        a, k, b = self._arrays, self._k, self.num_envs
        act = self._actions(action)
        self._ready()  # before the actions are written: a worker may still be reading the last ones
        a["action"][k:] = act[k:]
        seq = self._send("step")
        # The results come in fresh arrays: this process's rows are written there directly,
        # the workers' are copied from shared memory, which the next step writes over.
        next_obs = np.empty((b, *self.observation_spec.shape), self._obs_dtype)
        reset_obs = np.empty_like(next_obs)
        reward, terminated, truncated = np.empty(b, np.float32), np.empty(b, np.bool_), np.empty(b, np.bool_)
        try:
            _, local_info = self._local.step_into(act[:k], next_obs[:k], reward[:k], terminated[:k], truncated[:k],
                                                  reset_obs[:k])
        except Exception:  # (a KeyboardInterrupt leaves the replies to the next call's _resync)
            self._settle(seq)
            raise
        infos = self._gather(seq)
        next_obs[k:], reward[k:] = a["next_obs"][k:], a["reward"][k:]
        terminated[k:], truncated[k:] = a["terminated"][k:], a["truncated"][k:]
        ended = terminated | truncated
        self._check_observations(next_obs)
        obs = next_obs
        if ended.any():
            obs = next_obs.copy()
            reset_obs[k:] = a["obs"][k:]
            obs[ended] = reset_obs[ended]
            self._check_observations(reset_obs[ended], "reset")
        return StepOutput(torch.from_numpy(next_obs), torch.from_numpy(reward), torch.from_numpy(terminated),
                          torch.from_numpy(truncated), torch.from_numpy(obs), self._join_infos([local_info, *infos]))

    def _join_infos(self, infos: list[EpisodeInfo | None]) -> EpisodeInfo | None:
        if all(i is None for i in infos):
            return None
        out = {k: np.full(self.num_envs, np.nan) for k in self.info_keys}
        for (lo, hi), info in zip(self.slices, infos, strict=True):
            if info is not None:
                for k, v in info.items():
                    out[k][lo:hi] = v
        return out

    def render(self) -> np.ndarray | None:
        raise UserError("rendering needs env.vectorization = 'sync' (the video command uses one in-process env)")

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for conn in self._conns:
            try:
                if self._broken is None:  # (a broken pipe may have part of a message in it: no command)
                    conn.send_bytes(pickle.dumps(("close", 0, None)))
            except OSError:
                pass
            conn.close()  # now: a worker blocked writing a reply, or reading the rest of one, exits
        for proc in self._procs:
            proc.join(timeout=5)
            if proc.is_alive():  # stuck in the env's code
                proc.terminate()
                proc.join(timeout=2)
            if proc.is_alive():
                proc.kill()
                proc.join(timeout=2)
            if not proc.is_alive():
                proc.close()  # its sentinel pipe now, not when the garbage collector finds it
        for conn in self._conns:
            MAIN_ENDS.discard(conn)
        # the shared memory goes back now, not when the garbage collector meets this env: a
        # Ctrl-C during that late free, at a moment no one chose, breaks multiprocessing's heap
        self._arrays = {}
        self._local.close()
