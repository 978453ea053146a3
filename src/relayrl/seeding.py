"""Every random stream of a run, derived from its one `seed` through `numpy.random.SeedSequence`.

A stream is `SeedSequence(seed, spawn_key=(stream, ...))`: the spawned child that NumPy's
`SeedSequence(seed).spawn()` would give, so no two streams of a run share numbers, for any seed
and any number of envs or actors. Envs, which Gymnasium seeds with integers (copy i of a batch
gets `base + i`, as Gymnasium's vector envs do), get a 62-bit base drawn from their own
stream; an integer-seeded generator has no spawn key, so it can coincide with none of the
spawned streams, and two drawn bases are 2**62 apart on average.

| stream | seeds |
|---|---|
| envs | the training env copies' resets (copy i: base + i) |
| exploration | the agent's generator: epsilon-greedy draws, SAC's noise, its torch generator |
| replay | the replay table's sampling and random removal |
| warmup | the random policy of `train.initial_collect_steps` |
| evaluation | evaluation k's env resets (base + 10,000 k + copy); one off the grid leaves k to the next |
| resume | the env resets of a resumed run whose envs could not be restored (base + env steps) |
| torch | torch's global generator: network initialisation |
| actors | actor k on Ray: its own envs / exploration / warmup streams, below (actors, k) |
"""

from __future__ import annotations

import hashlib
from typing import Any, SupportsInt, cast

import numpy as np

from relayrl.errors import UserError

STREAMS = ("envs", "exploration", "replay", "warmup", "evaluation", "resume", "torch", "actors")
MAX_SEED = 2**63 - 1  # what every consumer of a seed accepts (torch.manual_seed, SeedSequence, JSON)
EVAL_STRIDE = 10_000  # evaluation k resets its copies from base + EVAL_STRIDE * k


def restore_generator(gen: Any, state: Any) -> bool:
    """Put a torch generator's saved state (`state`, a uint8 tensor) back; True where it was. A
    state saved on another kind of device (a CUDA generator's 16 bytes, a CPU's 5,056) cannot
    be: the generator is seeded from it instead, so a run moved between a GPU and a CPU resumes
    (its draws differ from the run's there, as every number computed on another device does)."""
    if state.numel() == gen.get_state().numel():
        gen.set_state(state)
        return True
    gen.manual_seed(int.from_bytes(hashlib.sha256(state.cpu().numpy().tobytes()).digest()[:8], "little") & MAX_SEED)
    return False


def seed_problem(seed: object, name: str | None = "seed") -> str | None:
    """Why `seed` cannot seed a run, in one line (naming it `name`=, unless None: argparse names
    the flag itself); None where it is an integer in [0, MAX_SEED]."""
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)) or not 0 <= seed <= MAX_SEED:
        given = repr(seed) if name is None else f"{name}={seed!r}"
        return f"{given} is not valid; it must be an integer in [0, {MAX_SEED}]"
    return None


def check_seed(seed: object, name: str = "seed") -> int | None:
    """A seed a caller passes (None: unseeded): refused in one line where it is not an integer in
    [0, MAX_SEED], before NumPy or Gymnasium say it in their own words (or the error is taken for
    a broken file). Returns it as a Python int (Gymnasium's reset refuses a NumPy seed), or None."""
    if seed is None:
        return None
    if (problem := seed_problem(seed, name)) is not None:
        raise UserError(f"{problem}, or None (unseeded)")
    return int(cast(SupportsInt, seed))


class RunSeeds:
    """The streams of one run (or, below `actor(k)`, of one of its Ray actors)."""

    def __init__(self, seed: int, key: tuple[int, ...] = ()) -> None:
        if (problem := seed_problem(seed)) is not None:
            raise ValueError(problem)
        self.seed, self.key = seed, key

    def sequence(self, stream: str) -> np.random.SeedSequence:
        return np.random.SeedSequence(self.seed, spawn_key=(*self.key, STREAMS.index(stream)))

    def generator(self, stream: str) -> np.random.Generator:
        return np.random.default_rng(self.sequence(stream))

    def base(self, stream: str) -> int:
        """A 62-bit integer seed from `stream`, for APIs that take integers (env resets,
        torch.manual_seed); offsets added to it stay below 2**63."""
        return int(self.sequence(stream).generate_state(1, np.uint64)[0] >> np.uint64(2))

    def actor(self, index: int) -> RunSeeds:
        """The streams of Ray actor `index` (0, 1, ...), apart from the learner's and each other's."""
        return RunSeeds(self.seed, (*self.key, STREAMS.index("actors"), index))
