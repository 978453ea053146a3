"""FastAdam makes the same updates as torch.optim.Adam and round-trips its state."""

import pytest
import torch

from relayrl.nn import MLP
from relayrl.optim import FastAdam


def train(opt_factory, steps=20, state=None):
    torch.manual_seed(0)
    net = MLP(3, [8], 2)
    opt = opt_factory(net.parameters())
    if state is not None:
        opt.load_state_dict(state)
    x = torch.randn(16, 3)
    for _ in range(steps):
        opt.zero_grad()
        net(x).square().mean().backward()
        opt.step()
    return net, opt


def test_same_updates_as_torch_adam():
    ours, _ = train(lambda p: FastAdam(p, lr=1e-2, eps=1e-7))
    ref, _ = train(lambda p: torch.optim.Adam(p, lr=1e-2, eps=1e-7))
    for a, b in zip(ours.parameters(), ref.parameters(), strict=False):
        assert torch.allclose(a, b, atol=1e-6)


def test_state_dict_round_trip():
    net, opt = train(lambda p: FastAdam(p, lr=1e-2))
    state = opt.state_dict()
    other = FastAdam(MLP(3, [8], 2).parameters(), lr=0.5)
    other.load_state_dict(state)
    assert other.lr == 1e-2
    assert all(torch.equal(a, b) for a, b in zip(other.exp_avg, opt.exp_avg, strict=False))
    assert all(torch.equal(a, b) for a, b in zip(other.steps, opt.steps, strict=False))


def test_parameters_on_no_device_or_several_are_refused_when_built():
    with pytest.raises(ValueError, match=r"on one device; got them on \[\]"):
        FastAdam([torch.zeros(2)], lr=1e-3)  # a tensor that needs no grad is no trainable parameter


def test_a_parameter_without_a_gradient_is_left_as_torch_adam_leaves_it():
    """A layer a user's encoder leaves out of its forward pass gets no grad: torch.optim.Adam
    skips it, moments and step count included; the others step as usual."""
    def run(make):
        torch.manual_seed(0)
        used, spare = torch.nn.Linear(3, 2), torch.nn.Linear(3, 2)
        opt = make([*used.parameters(), *spare.parameters()])
        x = torch.randn(16, 3)
        for _ in range(5):
            opt.zero_grad()
            used(x).square().mean().backward()
            opt.step()
        return used, spare, opt

    ours_used, ours_spare, ours = run(lambda p: FastAdam(p, lr=1e-2))
    ref_used, ref_spare, _ = run(lambda p: torch.optim.Adam(p, lr=1e-2))
    for a, b in zip([*ours_used.parameters(), *ours_spare.parameters()],
                    [*ref_used.parameters(), *ref_spare.parameters()], strict=True):
        assert torch.allclose(a, b, atol=1e-6)
    assert [float(s) for s in ours.steps] == [5.0, 5.0, 0.0, 0.0]
