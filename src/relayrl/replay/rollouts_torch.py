"""Rollouts that stay torch tensors on the run's device: for a stateless torch env, whose
observations, actions and rewards are tensors there already (the PureJaxRL / Brax layout:
env, policy, rollout and GAE on one device, no host round trip). The table keeps the tensors
the actor wrote by reference, so the learner samples them without a copy.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from relayrl.replay.rollouts import RolloutWriter
from relayrl.replay.storage import Storage
from relayrl.replay.table import Table


class TensorItemStorage(Storage):
    """A table's storage holding each slot's item as a dict of tensors (views of what was
    inserted). `read` of one slot returns views; of several, stacked tensors. Only live items
    are checkpointed, as CPU copies."""

    def __init__(self, capacity: int, device: torch.device) -> None:
        self.device = device
        self.items: list[dict[str, torch.Tensor] | None] = [None] * capacity
        self.slot_key: np.ndarray | None = None  # the table's key map: -1 marks a free slot

    def bind(self, slot_key: np.ndarray) -> None:
        self.slot_key = slot_key

    def write(self, slots: np.ndarray, items: dict[str, torch.Tensor]) -> None:
        for j, slot in enumerate(slots.tolist()):
            self.items[slot] = {k: torch.as_tensor(v)[j].to(self.device) for k, v in items.items()}

    def read(self, slots: np.ndarray) -> dict[str, torch.Tensor]:
        rows = [self.items[s] for s in slots.tolist()]
        if any(r is None for r in rows):
            raise KeyError(f"TensorItemStorage: slots {slots.tolist()} hold no item")
        if len(rows) == 1:
            return {k: v.unsqueeze(0) for k, v in rows[0].items()}  # type: ignore[union-attr]
        return {k: torch.stack([r[k] for r in rows]) for k in rows[0]}  # type: ignore[index]

    def state_dict(self) -> dict[str, Any]:
        live = range(len(self.items)) if self.slot_key is None else np.flatnonzero(self.slot_key >= 0).tolist()
        return {"items": {s: {k: v.cpu().clone() for k, v in self.items[s].items()}  # type: ignore[union-attr]
                          for s in live if self.items[s] is not None}}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.items = [None] * len(self.items)
        for slot, item in state.get("items", {}).items():
            self.items[int(slot)] = {k: v.to(self.device) for k, v in item.items()}


class TensorRolloutWriter(RolloutWriter):
    """A RolloutWriter whose rollouts are tensors on `device`; its table must keep them as
    tensors (`tensor_rollout_queue`)."""

    def __init__(self, table: Table, steps: int, device: torch.device) -> None:
        super().__init__(table, steps)
        self.device = device

    def as_array(self, value: Any) -> torch.Tensor:
        return torch.as_tensor(value).to(self.device)  # a no-op for the stateless env's own tensors

    def needs_buffer(self, name: str, value: Any) -> bool:
        return True  # the table holds the last rollout's tensors by reference: never overwrite them

    def empty(self, value: torch.Tensor) -> torch.Tensor:
        return torch.empty((self.steps, *value.shape), dtype=value.dtype, device=self.device)


def tensor_rollout_queue(name: str, max_size: int, device: torch.device) -> Table:
    """`Table.queue` whose items stay tensors on `device` (see TensorItemStorage)."""
    table = Table.queue(name, max_size)
    table.set_storage(TensorItemStorage(max_size, device))
    return table
