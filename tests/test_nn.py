"""relayrl.nn: the MLP and twin MLP, and their hand-written gradients (mlp_fast) against
autograd for every activation in the registry."""

import copy

import pytest
import torch

from relayrl.config_fields import ACTIVATION_NAMES
from relayrl.nn import ACTIVATIONS, MLP, TwinMLP
from relayrl.nn.mlp_fast import (
    MLPFast,
    TwinMLPFast,
    clip_flat_grad_norm_,
    clip_grad_norm_,
    grad_buffers,
    supports,
)

ALL = sorted(ACTIVATIONS)


def _close(got, want, what):
    assert got.shape == want.shape, what
    assert torch.allclose(got, want, rtol=1e-5, atol=1e-6), what


@pytest.mark.parametrize("activation", ALL)
@pytest.mark.parametrize("rows", [None, 6])  # all rows in the loss / only the first 6 of 10
def test_mlp_gradients_equal_autograd(activation, rows):
    torch.manual_seed(0)
    net = MLP(5, [16, 8], 3, activation)
    x = torch.randn(10, 5, requires_grad=True)
    n = rows or 10
    g_out = torch.randn(n, 3)
    ref = net(x)
    (ref[:n] * g_out).sum().backward()
    fast = MLPFast(net)
    with torch.no_grad():
        out, saved = fast.forward(x.detach().clone())
        _close(out, ref.detach(), "forward")
        grads = fast.new_grads()
        g_x = fast.backward(g_out, saved, grads, rows=rows, input_grad=True)
    for g, p in zip(grads, net.parameters(), strict=True):
        _close(g, p.grad, "parameter gradient")
    _close(g_x, x.grad[:n], "input gradient")


@pytest.mark.parametrize("activation", ALL)
def test_mlp_input_gradient_alone_leaves_parameter_buffers_alone(activation):
    torch.manual_seed(0)
    net = MLP(4, [8], 2, activation)
    fast = MLPFast(net)
    flat, views = grad_buffers(net)
    with torch.no_grad():
        _, saved = fast.forward(torch.randn(3, 4))
        g_x = fast.backward(torch.ones(3, 2), saved, None, input_grad=True)
    assert g_x is not None and g_x.shape == (3, 4) and not flat.any()


@pytest.mark.parametrize("activation", ALL)
@pytest.mark.parametrize("hidden", [[7, 6], []])
def test_twin_mlp_gradients_equal_autograd(activation, hidden):
    torch.manual_seed(0)
    net = TwinMLP(5, hidden, activation)
    obs, act = torch.randn(9, 3), torch.randn(9, 2, requires_grad=True)
    gq = torch.randn(2, 9)
    ref = net(obs, act)  # [2, N]
    (ref * gq).sum().backward()
    fast = TwinMLPFast(net)
    with torch.no_grad():
        q, saved = fast.forward(torch.cat([obs, act.detach()], 1))
        _close(q, ref.detach(), "forward")
        grads = fast.new_grads()
        g_x = fast.backward(gq, saved, grads, input_grad=True)
    for g, p in zip(grads, net.parameters(), strict=True):
        _close(g, p.grad, "parameter gradient")
    _close(g_x[:, 3:], act.grad, "input gradient")


def test_twin_mlp_equals_separate_mlps():
    torch.manual_seed(0)
    critic = TwinMLP(5, [7, 6], "relu")
    obs, act = torch.randn(4, 3), torch.randn(4, 2)
    x = torch.cat([obs, act], 1)
    for i in range(2):
        h = x
        for j, (w, b) in enumerate(zip(critic.weights, critic.biases, strict=True)):
            h = h @ w[i] + b[i]
            h = torch.relu(h) if j < 2 else h
        assert torch.allclose(critic(obs, act)[i], h.squeeze(-1), atol=1e-6)


def test_twin_mlp_detached_params_give_input_gradients_only():
    critic = TwinMLP(5, [8], "relu")
    action = torch.randn(4, 2, requires_grad=True)
    critic(torch.randn(4, 3), action, detach_params=True).sum().backward()
    assert action.grad is not None and bool(action.grad.abs().sum() > 0)
    assert all(p.grad is None for p in critic.parameters())


def test_state_dict_keys_and_parameter_order():
    """Checkpoints and exported policies name parameters this way; the optimizers and the
    hand-written gradients rely on this order."""
    mlp = MLP(3, [4, 5], 2)
    assert list(mlp.state_dict()) == [f"layers.{i}.{k}" for i in range(3) for k in ("weight", "bias")]
    twin = TwinMLP(3, [4, 5])
    assert list(twin.state_dict()) == [*(f"weights.{i}" for i in range(3)), *(f"biases.{i}" for i in range(3))]
    clone = copy.deepcopy(twin)
    clone.load_state_dict(twin.state_dict())
    assert [p.shape for p in twin.parameters()] == [(2, 3, 4), (2, 4, 5), (2, 5, 1), (2, 1, 4), (2, 1, 5), (2, 1, 1)]


def test_fast_views_follow_in_place_updates():
    torch.manual_seed(0)
    net = MLP(4, [8], 2, "tanh")
    fast = MLPFast(net)
    x = torch.randn(3, 4)
    with torch.no_grad():
        net.load_state_dict({k: v + 1.0 for k, v in net.state_dict().items()})
        assert torch.allclose(fast.forward(x)[0], net(x), atol=1e-6)


def test_only_plain_networks_with_registered_activations_are_supported():
    assert supports(MLP(4, [8], 2, "elu")) and supports(TwinMLP(4, [8], "tanh"))
    assert not supports(torch.nn.Sequential(torch.nn.Linear(4, 2)))
    net = MLP(4, [8], 2)
    net.activation = "softsign"
    assert not supports(net)


def test_the_registry_holds_the_names_configs_offer():
    assert tuple(ACTIVATIONS) == ACTIVATION_NAMES


def test_grad_buffers_are_views_of_one_flat_buffer_in_parameter_order():
    net = MLP(3, [4], 2)
    flat, views = grad_buffers(net)
    assert [v.shape for v in views] == [p.shape for p in net.parameters()]
    views[-1].fill_(1.0)
    assert flat[-2:].tolist() == [1.0, 1.0] and flat[:-2].eq(0).all()


@pytest.mark.parametrize("max_norm", [1e-3, 1e3])  # clipping active / inactive
def test_clipping_equals_torch(max_norm):
    torch.manual_seed(0)
    net = MLP(5, [16, 8], 3)
    net(torch.randn(7, 5)).square().sum().backward()
    ref_grads = [p.grad.clone() for p in net.parameters()]
    flat, views = grad_buffers(net)
    torch._foreach_copy_(views, ref_grads)
    listed = [g.clone() for g in ref_grads]
    ref_norm = torch.nn.utils.clip_grad_norm_(net.parameters(), max_norm)
    assert torch.allclose(clip_flat_grad_norm_(flat, max_norm), ref_norm, rtol=1e-6)
    assert torch.allclose(clip_grad_norm_(listed, max_norm), ref_norm, rtol=1e-6)
    for v, g, p in zip(views, listed, net.parameters(), strict=True):
        assert torch.allclose(v, p.grad, rtol=1e-5, atol=1e-8)
        assert torch.allclose(g, p.grad, rtol=1e-5, atol=1e-8)
