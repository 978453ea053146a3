"""SAC's critic, actor and alpha gradients computed by hand instead of by autograd.

Why, as for DQN (`agents/dqn/fast.py`): on a CPU a (256, 256) SAC update is ~16 matmuls of
[256, 256] size plus ~150 small ops, and autograd's graph, AccumulateGrad nodes, transposes
and the three `backward()` calls cost ~4.5 ms of a ~17.5 ms update (BENCHMARKS.md, "Where
the time of a SAC update goes"). Here each forward pass keeps its activations and the chain
rule is written out with the kernels autograd would call. The maths is that of `losses.py`:
tests/test_sac_fast.py checks every gradient against those losses + `backward()`.

Shapes: N batch rows, A action dims, critics' weights [2, in, out] (`TwinCritic`).
"""

from __future__ import annotations

import torch

from relayrl.agents.dqn.fast import _BACKWARD, _FORWARD, MLPView
from relayrl.agents.sac.losses import tanh_gaussian
from relayrl.agents.sac.networks import TwinCritic
from relayrl.networks import MLP

Tensor = torch.Tensor


def supports(actor: torch.nn.Module, critic: torch.nn.Module) -> bool:
    """Whether these networks have hand-written gradients here."""
    return (type(actor) is MLP and actor.activation in _BACKWARD
            and type(critic) is TwinCritic and critic.activation in _BACKWARD)


class TwinView:
    """Detached views of a TwinCritic's parameters (they follow in-place optimizer steps)."""

    def __init__(self, net: TwinCritic) -> None:
        self.activation = net.activation
        self.weight = [w.detach() for w in net.weights]  # [2, in, out]
        self.weight_t = [w.transpose(1, 2) for w in self.weight]  # [2, out, in]
        self.bias = [b.detach() for b in net.biases]  # [2, 1, out]
        # Gradients are returned in net.parameters() order: every weight, then every bias.
        self.order = [*range(0, 2 * len(self.weight), 2), *range(1, 2 * len(self.weight), 2)]

    def forward(self, x: Tensor) -> tuple[Tensor, list[Tensor], list[Tensor | None]]:
        """Q [2, N] from x [N, in], the input of every layer, and the pre-activations elu needs."""
        act, keep_pre = _FORWARD[self.activation], self.activation == "elu"
        inputs: list[Tensor] = []
        pre: list[Tensor | None] = []
        last = len(self.weight) - 1
        for i in range(last):
            inputs.append(x)
            x = torch.baddbmm(self.bias[i], x, self.weight[i]) if i else torch.matmul(x, self.weight[i]) + self.bias[i]
            pre.append(x if keep_pre else None)
            x = act(x)  # [2, N, out]
        inputs.append(x)
        # The 1-wide head as multiply-and-sum, as TwinCritic.forward does (a degenerate bmm is slow).
        return (x * self.weight_t[last]).sum(-1) + self.bias[last].squeeze(-1), inputs, pre

    def backward(self, gq: Tensor, inputs: list[Tensor], pre: list[Tensor | None], params: bool = True,
                 input_grad: bool = False) -> tuple[list[Tensor], Tensor | None]:
        """From gq = d loss / d Q [2, N]: the gradients of [W0, W1, ..., b0, b1, ...] (when
        `params`) and d loss / d x [N, in] summed over both critics (when `input_grad`)."""
        back = _BACKWARD[self.activation]
        last = len(self.weight) - 1
        grads: list[Tensor] = [torch.empty(0)] * (2 * (last + 1))  # [W0, b0, W1, b1, ...] as filled
        x = inputs[last]  # [2, N, h]
        if params:
            grads[2 * last] = torch.bmm(x.transpose(1, 2), gq.unsqueeze(-1))  # [2, h, 1]
            grads[2 * last + 1] = gq.sum(1).view(-1, 1, 1)  # [2, 1, 1]
        g = gq.unsqueeze(-1) * self.weight_t[last]  # [2, N, h]
        for i in range(last - 1, -1, -1):
            g = back(g, pre[i], inputs[i + 1])  # d loss / d pre-activation [2, N, out]
            x = inputs[i]
            if params:
                grads[2 * i] = torch.matmul(x.transpose(-1, -2), g)  # [2, in, out] (layer 0: x [N, in])
                grads[2 * i + 1] = g.sum(1, keepdim=True)  # [2, 1, out]
            if i or input_grad:
                g = torch.bmm(g, self.weight_t[i])  # [2, N, in]
        return [grads[j] for j in self.order] if params else [], g.sum(0) if input_grad else None


@torch.no_grad()
def sample_and_log_prob(actor: MLPView, obs: Tensor, noise: Tensor, log_std_min: float, log_std_max: float
                        ) -> tuple[Tensor, Tensor, tuple]:
    """`losses.tanh_gaussian` on the actor's heads: a [N, A], log pi(a|s) [N], and what the
    backward pass needs."""
    out, inputs, pre = actor.forward(obs)  # [N, 2A]
    mean, raw = out.chunk(2, dim=-1)
    log_std = raw.clamp(log_std_min, log_std_max)
    a, log_prob = tanh_gaussian(mean, log_std, noise)
    return a, log_prob, (inputs, pre, raw, log_std.exp(), noise, a)


def actor_head_grad(g_a: Tensor, g_logp: Tensor, saved: tuple, log_std_min: float, log_std_max: float) -> Tensor:
    """d loss / d [mean, raw log_std] [N, 2A] from d loss / d a [N, A] and d loss / d log pi [N].

    a = tanh(u), u = mean + std * noise: da/du = 1 - a^2; log pi = sum(-log_std - 2 (log 2 -
    u - softplus(-2u))) + const: d log pi / du = 2 tanh(u) = 2a, d log pi / d log_std = -1
    (noise held fixed); the clamp passes gradient where min <= raw <= max, as torch's does.
    """
    _, _, raw, std, noise, a = saved
    g_logp = g_logp.unsqueeze(-1)  # [N, 1]
    g_u = g_a * (1.0 - a.square()) + 2.0 * g_logp * a  # [N, A]
    g_log_std = (g_u * std * noise - g_logp) * ((raw >= log_std_min) & (raw <= log_std_max))
    return torch.cat([g_u, g_log_std], dim=-1)
