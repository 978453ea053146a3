"""Replay with Reverb's model: Tables (sampler, remover, rate limiter) fed by writers.

    table = Table("replay", max_size=100_000, sampler=Prioritized(0.6), remover=Fifo(),
                  rate_limiter=SampleToInsertRatio(32, min_size_to_sample=1_000, error_buffer=8_192))
    writer = TransitionWriter(table, num_envs, obs_spec, action_spec, gamma=0.99, n_step=3)
    actor = Actor(env, policy, observers=[writer])
    batch, info = table.sample(64)
"""

from relayrl.replay.rate_limiters import MinSize, Queue, RateLimiter, SampleToInsertRatio, Stack
from relayrl.replay.selectors import Fifo, Lifo, MaxHeap, MinHeap, Prioritized, Selector, Uniform
from relayrl.replay.storage import ItemStorage
from relayrl.replay.table import RateLimiterTimeout, SampleInfo, Table
from relayrl.replay.writers import SequenceBatch, SequenceWriter, TransitionWriter

Sequence = SequenceBatch  # the name SequenceWriter items had before; SequenceBatch does not shadow typing.Sequence

__all__ = [
    "Fifo", "ItemStorage", "Lifo", "MaxHeap", "MinHeap", "MinSize", "Prioritized", "Queue", "RateLimiter",
    "RateLimiterTimeout", "SampleInfo", "SampleToInsertRatio", "Selector", "Sequence", "SequenceBatch",
    "SequenceWriter", "Stack", "Table", "TransitionWriter", "Uniform",
]
