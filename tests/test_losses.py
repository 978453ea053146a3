"""DQN losses against hand-computed TD targets."""

import pytest
import torch
from torch import nn

from relayrl.agents.dqn import dqn_loss, td_targets
from relayrl.types import Batch


class TableQ(nn.Module):
    """Q(s, .) read from a fixed table indexed by obs[:, 0]: hand-checkable values."""

    def __init__(self, table):
        super().__init__()
        self.table = nn.Parameter(torch.tensor(table, dtype=torch.float32))

    def forward(self, obs):
        return self.table[obs[:, 0].long()]


def make_batch(weight=None):
    # states 0 and 1 act; next states 2 and 3
    return Batch(
        obs=torch.tensor([[0.0], [1.0]]),
        action=torch.tensor([1, 0]),
        reward=torch.tensor([1.0, 2.0]),
        next_obs=torch.tensor([[2.0], [3.0]]),
        discount=torch.tensor([0.9, 0.0]),  # second transition terminated
        weight=weight,
    )


ONLINE = [[0.0, 5.0], [3.0, 0.0], [1.0, 4.0], [6.0, 2.0]]
TARGET = [[0.0, 0.0], [0.0, 0.0], [10.0, 7.0], [8.0, 9.0]]


def test_dqn_target_uses_max_of_target_net():
    y = td_targets(TableQ(ONLINE), TableQ(TARGET), make_batch(), double=False)
    # 1 + 0.9 * max(10, 7) = 10; terminated: 2 + 0 = 2
    assert torch.allclose(y, torch.tensor([10.0, 2.0]))


def test_double_dqn_selects_with_online_evaluates_with_target():
    y = td_targets(TableQ(ONLINE), TableQ(TARGET), make_batch(), double=True)
    # online argmax at state 2 is action 1 -> target value 7: 1 + 0.9 * 7 = 7.3
    assert torch.allclose(y, torch.tensor([7.3, 2.0]))


def test_no_target_network_uses_online_weights():
    y = td_targets(TableQ(ONLINE), None, make_batch(), double=True)
    # max online Q at state 2 is 4: 1 + 0.9 * 4 = 4.6
    assert torch.allclose(y, torch.tensor([4.6, 2.0]))


def test_mse_loss_is_elementwise_squared_error_without_half():
    loss, metrics = dqn_loss(TableQ(ONLINE), TableQ(TARGET), make_batch(), double=False, loss="mse")
    # q = [5, 3], y = [10, 2]: ((5-10)^2 + (3-2)^2) / 2 = 13
    assert loss.item() == pytest.approx(13.0)
    assert torch.allclose(metrics["td_error"], torch.tensor([-5.0, 1.0]))


def test_huber_loss_is_linear_beyond_delta():
    loss, _ = dqn_loss(TableQ(ONLINE), TableQ(TARGET), make_batch(), double=False, loss="huber")
    # |-5| > 1: 5 - 0.5 = 4.5; |1| <= 1: 0.5 * 1 = 0.5; mean 2.5
    assert loss.item() == pytest.approx(2.5)


def test_importance_weights_scale_elementwise_loss():
    loss, _ = dqn_loss(TableQ(ONLINE), TableQ(TARGET), make_batch(torch.tensor([0.5, 2.0])),
                       double=False, loss="mse")
    assert loss.item() == pytest.approx((0.5 * 25 + 2.0 * 1) / 2)


def test_gradient_flows_only_into_taken_actions_of_online_net():
    online, target = TableQ(ONLINE), TableQ(TARGET)
    loss, _ = dqn_loss(online, target, make_batch(), double=False, loss="mse")
    loss.backward()
    expected = torch.zeros(4, 2)
    expected[0, 1] = 2 * (5 - 10) / 2
    expected[1, 0] = 2 * (3 - 2) / 2
    assert torch.allclose(online.table.grad, expected)
    assert target.table.grad is None
