"""VariableContainer versions and snapshots; WeightPuller keeps an actor's copy fresh."""

import torch
from torch import nn

from relayrl.training.variables import VariableContainer, WeightPuller


def test_push_snapshots_and_versions():
    vc = VariableContainer()
    assert vc.pull() == (0, None)
    w = [torch.ones(2), torch.zeros(3)]
    assert vc.push(w) == 1
    w[0].add_(5.0)  # the learner keeps training after a push
    version, got = vc.pull()
    assert version == 1 and torch.equal(got[0], torch.ones(2))
    assert vc.pull(newer_than=1) == (1, None)
    vc.push(w)
    assert vc.pull(newer_than=1)[0] == 2


def test_puller_copies_in_place_at_most_every_interval():
    learner_net, actor_net = nn.Linear(2, 2), nn.Linear(2, 2)
    view = actor_net.weight.detach().numpy()  # NumPy views of the actor's params must stay valid
    vc = VariableContainer()
    puller = WeightPuller(vc, actor_net, interval=100)
    assert not puller.maybe_pull(0)  # nothing pushed yet
    vc.push(list(learner_net.parameters()))
    assert not puller.maybe_pull(50)  # too soon after the last pull at step 0
    assert puller.maybe_pull(100)
    assert torch.equal(actor_net.weight, learner_net.weight) and (view == learner_net.weight.detach().numpy()).all()
    assert not puller.maybe_pull(200)  # nothing newer
    state = vc.state_dict()
    other = VariableContainer()
    other.load_state_dict(state)
    assert other.version == 1
