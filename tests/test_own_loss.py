"""A loss of one's own, as README's "Your own loss or algorithm" shows: the reference update
subclassed and given to an agent built with hand_written=False trains with it."""

import numpy as np
import torch

from relayrl.agents.dqn import DQNAgent, DQNConfig
from relayrl.agents.dqn.update import DQNUpdate
from relayrl.specs import ArraySpec, DiscreteSpec
from relayrl.types import Batch


class CQLUpdate(DQNUpdate):
    """DQN's loss plus a conservative penalty: logsumexp of Q over the actions, less Q of the taken one."""

    def losses(self, batch, target_q):
        loss, metrics = super().losses(batch, target_q)
        q = self.online(batch.obs)
        penalty = (torch.logsumexp(q, dim=1) - q.gather(1, batch.action.long().view(-1, 1)).squeeze(1)).mean()
        return loss + 0.5 * penalty, {**metrics, "cql": penalty.detach()}


def agent(update: type[DQNUpdate] | None = None) -> DQNAgent:
    torch.manual_seed(0)
    made = DQNAgent(ArraySpec((4,), torch.float32), DiscreteSpec(2), DQNConfig(hidden=[16]), torch.device("cpu"),
                    np.random.default_rng(0), hand_written=False)
    if update is not None:
        made.update = update(made.online, made.target, made.optimizer, made.cfg)
    return made


def test_a_subclassed_reference_update_is_what_trains():
    g = torch.Generator().manual_seed(1)
    batch = Batch(torch.randn(32, 4, generator=g), torch.randint(0, 2, (32,), generator=g), torch.ones(32),
                  torch.randn(32, 4, generator=g), torch.full((32,), 0.99), None)
    plain, own = agent(), agent(CQLUpdate)
    assert "cql" not in plain.train(batch)
    metrics = own.train(batch)
    assert float(metrics["cql"]) > 0
    assert not torch.equal(plain.online.layers[0].weight, own.online.layers[0].weight)  # another loss, other weights
