"""Batch-aware metrics, as observers of batched transitions.

Per-env accumulators are sized from the first transition they see, so no metric is ever told
the batch size (TF-Agents' `AverageReturnMetric(batch_size=...)` trap cannot happen).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from relayrl.arrays import to_numpy
from relayrl.compile import numba_available
from relayrl.core import Observer
from relayrl.types import Transition

FINISHED_KEPT = 100_000  # finished episodes kept for TensorBoard between logs (the oldest go first)


def on_device(x: Any) -> bool:
    """A tensor on a device other than the CPU (whose reads from the host wait for it)."""
    return isinstance(x, torch.Tensor) and x.device.type != "cpu"


class EnvironmentSteps(Observer):
    """Env steps taken: B per batched step."""

    def __init__(self) -> None:
        self.value = 0

    def __call__(self, t: Transition) -> None:
        self.value += t.reward.shape[0]

    def result(self) -> int:
        return self.value

    def state_dict(self) -> dict[str, Any]:
        return {"value": self.value}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.value = int(state["value"])


class EpisodeStats(Observer):
    """Running return and length per env; completed episodes go into windows of `buffer_size`.

    The four episode metrics read from one instance, so each batched step is accumulated once.
    """

    def __init__(self, buffer_size: int | None = 10) -> None:  # None: keep all
        self.returns: deque[float] = deque(maxlen=buffer_size)
        self.lengths: deque[int] = deque(maxlen=buffer_size)
        self.info: dict[str, deque[float]] = {}  # env.info_keys values at episode ends, same window
        self.episodes = 0
        # (env step, return, length) of each finished episode, while `step_fn` (the run's env
        # step counter, read only where episodes end) is set: TensorBoard's per-episode points
        self.step_fn: Callable[[], int] | None = None
        self.finished: deque[tuple[int, float, int]] = deque(maxlen=FINISHED_KEPT)
        self._ret: np.ndarray | None = None
        self._len: np.ndarray | None = None
        self._done: np.ndarray | None = None
        self._accumulate: Callable[..., Any] | None = None  # None: the NumPy path
        # A device's (reward, terminated, truncated, episode_info, env step) until `flush`
        self._staged: list[tuple[Any, Any, Any, dict[str, Any] | None, int | None]] = []
        if numba_available():
            from relayrl.metrics_fast import accumulate
            self._accumulate = accumulate

    def __call__(self, t: Transition) -> None:
        if on_device(t.reward):
            # A GPU's steps are read in one copy per collect call (`flush`), not three host
            # syncs per batched step; each keeps the env step it was taken at.
            self._staged.append((t.reward, t.terminated, t.truncated, t.episode_info,
                                 None if self.step_fn is None else self.step_fn()))
            return
        self._add(to_numpy(t.reward), to_numpy(t.terminated), to_numpy(t.truncated), t.episode_info,
                  self.step_fn)

    def flush(self) -> None:
        """Accumulate the steps staged from a device (one host copy for all of them)."""
        if not self._staged:
            return
        staged, self._staged = self._staged, []
        rows = torch.stack([torch.stack([r.float(), term.float(), trunc.float()])
                            for r, term, trunc, _, _ in staged]).cpu().numpy()  # [T, 3, B]
        for (*_, episode_info, step), (reward, terminated, truncated) in zip(staged, rows, strict=True):
            info = None if not episode_info else {k: to_numpy(v) for k, v in episode_info.items()}
            self._add(reward.astype(np.float32), terminated > 0, truncated > 0, info, step)

    def _add(self, reward: np.ndarray, terminated: np.ndarray, truncated: np.ndarray,
             episode_info: dict[str, Any] | None, step: Callable[[], int] | int | None) -> None:
        """One batched step's bookkeeping; `step`: the env step it was taken at (or what reads
        it, called only where an episode ended), None where no one asked."""
        if self._ret is None or self._ret.shape[0] != reward.shape[0]:
            self._ret = np.zeros(reward.shape[0], np.float64)
            self._len = np.zeros(reward.shape[0], np.int64)
            self._done = np.zeros(reward.shape[0], np.bool_)
        assert self._len is not None and self._done is not None
        # NumPy, not torch, for these [B] arrays: a tiny torch op costs several times more.
        if self._accumulate is not None:
            if not self._accumulate(self._ret, self._len, reward, terminated, truncated, self._done):
                return
            done = self._done
        else:
            self._ret += reward
            self._len += 1
            done = terminated | truncated
        if done.any():
            ended = np.flatnonzero(done)
            for i in ended:
                self.returns.append(float(self._ret[i]))
                self.lengths.append(int(self._len[i]))
            if step is not None:
                at = step() if callable(step) else step
                self.finished.extend((at, float(self._ret[i]), int(self._len[i])) for i in ended)
            for key, values in (episode_info or {}).items():
                self._info_window(key).extend(float(values[i]) for i in ended)
            self.episodes += int(done.sum())
            self._ret[done] = 0.0
            self._len[done] = 0

    def add_finished(self, returns: list[float], lengths: list[int], info: dict[str, list[float]]) -> None:
        """Count episodes that finished elsewhere (a remote actor's `EpisodeLog.take()`)."""
        self.returns.extend(returns)
        self.lengths.extend(lengths)
        if self.step_fn is not None:  # they finished on actors: at the step they are counted
            step = self.step_fn()
            self.finished.extend((step, float(r), int(n)) for r, n in zip(returns, lengths, strict=True))
        for key, values in info.items():
            self._info_window(key).extend(values)
        self.episodes += len(returns)

    def take_finished(self) -> list[tuple[int, float, int]]:
        """The finished episodes recorded since the last call, oldest first."""
        out = list(self.finished)
        self.finished.clear()
        return out

    def _info_window(self, key: str) -> deque[float]:
        """The window of `key`'s values, as long as the returns' window."""
        window = self.info.get(key)
        if window is None:  # made once per key, not at every episode's end as setdefault's argument would be
            window = self.info[key] = deque(maxlen=self.returns.maxlen)
        return window

    def info_means(self) -> dict[str, float]:
        """Mean of each info key over its window (keys with no finished episode left out)."""
        return {k: float(np.mean(w)) for k, w in self.info.items() if w}

    def reset_running(self) -> None:
        """Forget episodes in progress (after an env reset that the stats did not see); the
        steps staged before it still count."""
        self.flush()
        self._ret = None
        self._len = None

    def state_dict(self) -> dict[str, Any]:
        self.flush()
        running = None if self._ret is None else (self._ret.copy(), self._len.copy())  # type: ignore[union-attr]
        return {"returns": list(self.returns), "lengths": list(self.lengths), "episodes": self.episodes,
                "running": running, "info": {k: list(w) for k, w in self.info.items()},
                "finished": list(self.finished)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restores episodes in progress too; call `reset_running()` after if the envs were
        reset rather than restored."""
        self.returns = deque(state["returns"], maxlen=self.returns.maxlen)
        self.lengths = deque(state["lengths"], maxlen=self.lengths.maxlen)
        self.episodes = int(state["episodes"])
        self.finished = deque((tuple(e) for e in state.get("finished", [])), maxlen=FINISHED_KEPT)
        self.info = {}
        for key, values in state.get("info", {}).items():
            self._info_window(key).extend(values)
        self.reset_running()
        if state.get("running") is not None:
            ret, length = state["running"]
            self._ret, self._len = np.array(ret, np.float64), np.array(length, np.int64)
            self._done = np.zeros(self._ret.shape[0], np.bool_)


class _Reading:
    """One number read off an `EpisodeStats` (TF-Agents' metric objects, `result()`)."""

    def __init__(self, stats: EpisodeStats) -> None:
        self.stats = stats


class AverageReturn(_Reading):
    """Mean return of the last `buffer_size` completed episodes (nan before the first)."""

    def result(self) -> float:
        return float(np.mean(self.stats.returns)) if self.stats.returns else float("nan")


class AverageEpisodeLength(_Reading):
    def result(self) -> float:
        return float(np.mean(self.stats.lengths)) if self.stats.lengths else float("nan")


class NumberOfEpisodes(_Reading):
    def result(self) -> int:
        return self.stats.episodes
