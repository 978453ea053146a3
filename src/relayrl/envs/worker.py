"""The worker side of async envs (`envs/vector.py`): how the copies are shared out, the shared
arrays' views, and the loop a worker process serves commands in.

A worker steps its slice with the in-process `GymBatchEnv`, reads actions from and writes results
into shared memory, and answers each command over its pipe with `MAGIC` and a pickled
(status, seq, value). Its failures travel as the main process raises them (`worker_failure`).
"""

from __future__ import annotations

import contextlib
import os
import pickle
import random
import signal
import struct
import traceback
import weakref
import zlib
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any, cast

import cloudpickle
import numpy as np
import torch

from relayrl.envs.gym import GymBatchEnv
from relayrl.errors import UserError


def usable_cpus() -> int:
    """The cores this process may run on (its affinity mask: `taskset`, container cpusets),
    which can be far fewer than the machine's `os.cpu_count()`."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # no sched_getaffinity (macOS, Windows)
        return os.cpu_count() or 1


def worker_slices(num_envs: int, num_workers: int) -> list[tuple[int, int]]:
    """Contiguous [lo, hi) slices of the copies, the main process's first, then one per worker
    (`num_workers`, 0: one per core beside the main's, never more than the copies allow);
    sizes differ by at most 1."""
    workers = num_workers or max(1, usable_cpus() - 1)
    n = 1 + max(0, min(workers, num_envs - 1))
    bounds = np.linspace(0, num_envs, n + 1).round().astype(int)
    return [(int(lo), int(hi)) for lo, hi in zip(bounds[:-1], bounds[1:], strict=True)]


SharedLayout = dict[str, tuple[tuple[int, ...], np.dtype]]  # a shared array's name -> (shape, dtype)


def shared_views(raw: dict[str, Any], layout: SharedLayout) -> dict[str, np.ndarray]:
    """NumPy views on the shared raw arrays (made again in a spawned worker, which gets `raw` pickled)."""
    return {k: np.frombuffer(raw[k], dtype=dtype, count=int(np.prod(shape))).reshape(shape)
            for k, (shape, dtype) in layout.items()}


# The main process's ends of every async env's pipes, its own env's included. A forked worker
# inherits them all and closes them: an inherited copy would keep a pipe open after its env's
# owner is gone (the main process SIGKILLed, or another env dropped without close()), so that
# env's workers would never read EOF and exit. A spawned worker inherits none.
MAIN_ENDS: weakref.WeakSet[Connection] = weakref.WeakSet()


def global_rng_seed(lo: int) -> int:
    """A seed for the global RNGs of the worker whose slice starts at copy `lo`: derived from
    this process's `np.random` state without drawing from it, distinct per worker. So it is a
    function of that state, as everything else a seeded script does: two envs made with no
    draw from `np.random` between them give their workers the same streams."""
    # The legacy tuple (numpy's stub types get_state()'s default as the dict of legacy=False)
    state = cast("tuple[str, np.ndarray, int, int, float]", np.random.get_state())
    return (zlib.crc32(state[1].tobytes()) + lo) % 2**32


# Pickled commands up to this size go out in one write (multiprocessing's Connection writes
# the length and the bytes together below 16 KiB): an interrupt sends all of one or none of it.
ONE_WRITE = 16_000


# Every reply starts with these bytes, after the Connection's length header: a reader whose
# stream lost bytes to an interrupt (see AsyncGymBatchEnv._fill) finds out at the next reply.
MAGIC = b"RLRW"
LENGTH = struct.Struct("!i")  # multiprocessing's Connection length header


def serve(conn: Connection, fns_pickled: bytes, lo: int, hi: int, raw: dict[str, Any], layout: SharedLayout,
            time_limit_terminates: bool, rng_seed: int) -> None:
    """Serve commands until "close": step, reset, info_keys, get_state, state_problem, set_state."""
    for end in list(MAIN_ENDS):  # see MAIN_ENDS
        end.close()
    # Ctrl-C reaches the terminal's whole process group: the main process reports it and closes
    # the workers, which must still answer it meanwhile. SIGTERM (close()'s last resort, and
    # multiprocessing's at exit) kills, whatever handler the forked main process had installed.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    np.random.seed(rng_seed)  # forked, they would repeat the main process's draws
    random.seed(rng_seed)
    torch.manual_seed(rng_seed)
    a = shared_views(raw, layout)
    env: GymBatchEnv | None = None
    try:
        made = _outcome(0, lambda: GymBatchEnv(cloudpickle.loads(fns_pickled), time_limit_terminates, first_copy=lo))
        env = made[2] if made[0] == "ok" else None
        reply = made if env is None else ("ok", 0, None)  # the main process waits for this "ok"
        while True:
            conn.send_bytes(MAGIC + pickle.dumps(reply))
            if env is None:
                break
            cmd, seq, arg = pickle.loads(conn.recv_bytes())
            if cmd == "close":
                break
            reply = _outcome(seq, _serve, env, a, lo, hi, cmd, arg)
    except (EOFError, OSError):  # the main process's end is closed (it exited, or dropped the env mid-reply)
        pass
    finally:
        if env is not None:
            env.close()
        conn.close()


def _outcome(seq: int, work: Callable[..., Any], *args: Any) -> tuple[str, int, Any]:
    """A worker's reply to command `seq`: ("ok", seq, work(*args)), or its failure as the main
    process raises it: a UserError as its one line (bad input met while making or stepping a
    copy), any other failure of the env's code with its traceback and, where it pickles, the
    exception itself (`worker_failure`)."""
    try:
        return ("ok", seq, work(*args))
    except UserError as e:
        return ("user_error", seq, str(e))
    except Exception as e:
        return ("error", seq, (traceback.format_exc(), _pickled(e)))


def _pickled(e: Exception) -> bytes | None:
    """`e` pickled, where it pickles (whether it loads back is the main process's to find)."""
    try:
        return cloudpickle.dumps(e)
    except Exception:
        return None


def worker_failure(w: int, trace: str, pickled: bytes | None) -> Exception:
    """What the main process raises for worker w's failure: the env's own exception, as a sync
    env raises it (so `except` clauses, and tools that catch some types, such as Optuna's
    `catch`, see the same type), with its traceback in the worker as a note; a RuntimeError
    carrying that traceback where the exception does not load here."""
    exc = None
    if pickled is not None:
        with contextlib.suppress(Exception):
            exc = pickle.loads(pickled)
    if isinstance(exc, Exception):
        trace = trace.rstrip()
        # the traceback ends with the exception's notes (GymBatchEnv's copy it names), which it
        # carries here too: said once, as its own notes
        said = "\n".join(getattr(exc, "__notes__", []))
        if said and trace.endswith("\n" + said):
            trace = trace[:-len(said)].rstrip()
        exc.add_note(f"(raised in env worker {w}; its traceback there:)\n{trace}")
        return exc
    return RuntimeError(f"env worker {w} failed:\n{trace}")


def _serve(env: GymBatchEnv, a: dict[str, np.ndarray], lo: int, hi: int, cmd: str, arg: Any) -> Any:
    """One command of a worker's slice [lo, hi): the reply's value."""
    if cmd == "step":  # straight into shared memory: reset observations into "obs"
        # A copy of the actions: an env may keep the one it was given (sync hands out a fresh
        # array each step), and the shared row is written over by the next step.
        return env.step_into(a["action"][lo:hi].copy(), a["next_obs"][lo:hi], a["reward"][lo:hi],
                             a["terminated"][lo:hi], a["truncated"][lo:hi], a["obs"][lo:hi])[1]
    if cmd == "reset":
        a["obs"][lo:hi] = env.reset(seed=None if arg is None else arg + lo).numpy()
    elif cmd == "info_keys":
        env.info_keys = arg
    elif cmd == "get_state":
        return env.get_state()
    elif cmd == "state_problem":
        return env.state_problem()
    elif cmd == "set_state":
        env.set_state(arg)
    elif cmd != "sync":  # "sync" only answers: see AsyncGymBatchEnv._resync
        raise ValueError(f"unknown env worker command {cmd!r}")
    return None
