"""EpisodeStats' per-step accumulation in one compiled loop (numba, the `relayrl[fast]` extra).

The NumPy path spends about eight array calls on [B] arrays every batched step, whose fixed
costs are most of its time; this loop does the same in one call. Without numba, or with
RELAYRL_NUMBA=0, `EpisodeStats` takes the NumPy path; tests/test_metrics.py checks both agree.
"""

from __future__ import annotations

import numpy as np

from relayrl.compile import njit


@njit
def accumulate(ret: np.ndarray, length: np.ndarray, reward: np.ndarray, terminated: np.ndarray,
               truncated: np.ndarray, done: np.ndarray) -> int:
    """ret += reward (in float64, as NumPy's mixed-type add), length += 1, done = terminated |
    truncated, all per env; returns how many episodes ended."""
    ended = 0
    for i in range(ret.size):
        ret[i] += np.float64(reward[i])
        length[i] += 1
        d = terminated[i] or truncated[i]
        done[i] = d
        ended += d
    return ended
