"""Builds a run's replay (Table + TransitionWriter) from its config.

The rate limiter is what decides how many gradient steps follow each collect iteration, in
one process as on Ray: samples_per_insert defaults to gradient_steps * batch_size /
collect_steps, and the error buffer to one iteration's worth of samples, so
`collect_steps` / `gradient_steps` in a preset mean what they say at any env.num_envs.
"""

from __future__ import annotations

from pathlib import Path

from relayrl.config import Config
from relayrl.errors import ConfigError
from relayrl.replay import (
    Fifo,
    MinSize,
    Prioritized,
    RateLimiter,
    SampleToInsertRatio,
    Table,
    TransitionWriter,
    Uniform,
)
from relayrl.specs import Spec


def env_steps_per_iteration(c: Config) -> int:
    b = c.env.num_envs
    return -(-c.train.collect_steps // b) * b  # the actor steps all envs together


def rate_limiter(c: Config) -> RateLimiter:
    r = c.replay
    min_size = r.min_size_to_sample or max(1, c.train.initial_collect_steps or c.agent.batch_size)
    if min_size > r.size:
        raise ConfigError(f"replay.min_size_to_sample={min_size} is more than replay.size={r.size}")
    per_iter = env_steps_per_iteration(c)
    # The nominal ratio (gradient_steps per collect_steps env steps), not per actual
    # iteration: with N envs an iteration may take more env steps than collect_steps (all
    # copies step together), and the update-to-data ratio must not change with N.
    spi = r.samples_per_insert or c.train.gradient_steps * c.agent.batch_size / c.train.collect_steps
    if spi == 0:
        return MinSize(min_size)  # gradient_steps = 0: collect only
    burst = spi * per_iter
    buffer = r.error_buffer or burst
    if buffer < burst:
        raise ConfigError(f"replay.error_buffer={r.error_buffer:g} is too small for one process: one collect "
                          f"iteration inserts {per_iter} items worth {burst:g} samples; use >= {burst:g} or 0")
    return SampleToInsertRatio(spi, min_size, buffer)


def build_replay(c: Config, obs_spec: Spec, action_spec: Spec, run_root: Path) -> tuple[Table, TransitionWriter]:
    r = c.replay
    sampler = Prioritized(r.priority_exponent) if r.sampler == "prioritized" else Uniform()
    table = Table("replay", r.size, sampler=sampler, remover=Fifo(), rate_limiter=rate_limiter(c), seed=c.seed + 2)
    path = None
    if r.storage == "memmap":
        path = Path(r.path) if r.path else run_root / "replay"
    writer = TransitionWriter(table, c.env.num_envs, obs_spec, action_spec, gamma=c.agent.gamma,
                              n_step=r.n_step, path=path)
    return table, writer
