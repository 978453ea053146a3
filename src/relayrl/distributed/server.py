"""The replay server: one Table, one writer per rollout actor, and what each actor shipped.

A plain class, so it runs in-process in tests; the distributed run makes it a threaded Ray
actor, where the Table's blocking rate limiter then holds across every client: an actor's
insert waits in its own thread while the learner's sample goes on in another.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import numpy as np

from relayrl.config import from_dict
from relayrl.replay import RateLimiterTimeout, SampleInfo
from relayrl.replay.steps import StepChunk
from relayrl.specs import Spec
from relayrl.training.replay_setup import build_shared_replay


class ReplayServer:
    def __init__(self, config: dict[str, Any], obs_spec: Spec, action_spec: Spec, run_root: str,
                 num_writers: int) -> None:
        c = from_dict(config)
        self.table, self.group = build_shared_replay(c, obs_spec, action_spec, Path(run_root), num_writers)
        self.shipped = [0] * num_writers  # env steps accepted from each actor
        # Each actor incarnation registers a token; chunks from an older incarnation (a dead
        # actor's last insert, still queued) are dropped, or they would join its episodes
        # to the new incarnation's.
        self.tokens: list[str | None] = [None] * num_writers
        self.intake_open = True  # False once the run halted its rollout actors: nothing more is counted
        self._counting = threading.Lock()  # `intake_open`'s check with the count it allows

    def register(self, index: int, token: str) -> None:
        """A (re)started actor: its writer forgets the open episodes of the one before."""
        self.tokens[index] = token
        self.group.restart_episodes(index)

    def close_intake(self) -> None:
        """Count no more chunks: the rollout actors were halted, but Ray kills them asynchronously,
        and a chunk one sent before it died may still arrive, or one the rate limiter held may be
        let through by a sample already asked for. After this `shipped` holds still, so a stopped
        run's checkpoint is named by the steps its driver counted (such a late chunk may still
        reach the table: a resume finds a few more transitions in it than it counts)."""
        with self._counting:
            self.intake_open = False

    def ingest(self, index: int, token: str, chunk: StepChunk) -> int:
        """Append an actor's chunk (blocking while the rate limiter says the learner lags);
        returns the env steps accepted from that actor so far."""
        if self.tokens[index] != token or not self.intake_open:
            return self.shipped[index]
        self.group.write_chunk(index, chunk)  # may block on the rate limiter
        with self._counting:
            if self.intake_open:  # not closed while the write waited
                self.shipped[index] += chunk.env_steps
        return self.shipped[index]

    def sample(self, batch_size: int, max_batches: int, timeout: float) -> list[tuple[Any, SampleInfo]]:
        """At least one batch, waiting up to `timeout` s for the rate limiter ([] if none came),
        then as many more as it allows now, up to `max_batches`: one RPC, several steps."""
        try:
            out = [self.table.sample(batch_size, timeout=timeout)]
        except RateLimiterTimeout:
            return []
        while len(out) < max_batches and self.table.samples_available() >= batch_size:
            out.append(self.table.sample(batch_size))
        # As NumPy: Ray pickles torch tensors through torch's own path, much slower than arrays
        # (bench/distributed.py --part server); RemoteTable turns them back into tensors.
        return [(type(b)(*(None if x is None else x.numpy() for x in b)), info) for b, info in out]

    def update_priorities(self, keys: np.ndarray, priorities: np.ndarray) -> None:
        self.table.update_priorities(keys, priorities)

    def info(self) -> dict[str, Any]:
        lim = self.table.rate_limiter
        return {"size": self.table.size, "inserts": lim.inserts, "samples": lim.samples,
                "shipped": list(self.shipped)}

    def state_dict(self, include_replay: bool = True) -> dict[str, Any]:
        # No ingest lock here: an insert blocked on the rate limiter holds it, and the learner
        # that would unblock it is the one waiting for this checkpoint. The Table's lock keeps
        # items and sampler consistent; a chunk caught half-inserted only loses its other half.
        return {"table": self.table.state_dict() if include_replay else None, "shipped": list(self.shipped)}

    def load_state_dict(self, state: dict[str, Any]) -> int:
        """Returns the replay items the load dropped (`Table.load_state_dict`)."""
        lost = self.table.load_state_dict(state["table"]) if state["table"] is not None else 0
        self.shipped = [int(x) for x in state["shipped"]]
        return lost
