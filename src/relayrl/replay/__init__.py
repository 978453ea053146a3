"""Replay: stores transitions from batched actors and samples training batches."""

from relayrl.replay.uniform import UniformReplay

__all__ = ["UniformReplay"]
