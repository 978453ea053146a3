"""SAC's loss gradients at the actor's heads, for the hand-written update of update.py.

The networks' backward passes are relayrl.nn.mlp_fast's; what is SAC's own is the
tanh-Gaussian sample's gradient with respect to the actor's [mean, log_std] outputs. The maths
is that of `losses.py`: tests/test_sac_fast.py checks every update against those losses +
`backward()`. Shapes: N batch rows, A action dims.
"""

from __future__ import annotations

import torch

from relayrl.agents.sac.losses import tanh_gaussian
from relayrl.nn.mlp_fast import MLPFast

Tensor = torch.Tensor


@torch.no_grad()
def sample_and_log_prob(actor: MLPFast, obs: Tensor, noise: Tensor, log_std_min: float, log_std_max: float
                        ) -> tuple[Tensor, Tensor, tuple]:
    """`losses.tanh_gaussian` on the actor's heads: a [N, A], log pi(a|s) [N], and what the
    backward pass needs."""
    out, saved = actor.forward(obs)  # [N, 2A]
    mean, raw = out.chunk(2, dim=-1)
    log_std = raw.clamp(log_std_min, log_std_max)
    a, log_prob = tanh_gaussian(mean, log_std, noise)
    return a, log_prob, (saved, raw, log_std.exp(), noise, a)


def actor_head_grad(g_a: Tensor, g_logp: Tensor, saved: tuple, log_std_min: float, log_std_max: float) -> Tensor:
    """d loss / d [mean, raw log_std] [N, 2A] from d loss / d a [N, A] and d loss / d log pi [N],
    for the first N rows of the sample that `saved` comes from.

    a = tanh(u), u = mean + std * noise: da/du = 1 - a^2; log pi = sum(-log_std - 2 (log 2 -
    u - softplus(-2u))) + const: d log pi / du = 2 tanh(u) = 2a, d log pi / d log_std = -1
    (noise held fixed); the clamp passes gradient where min <= raw <= max, as torch's does.
    """
    n = g_a.shape[0]
    raw, std, noise, a = (t[:n] for t in saved[1:])
    g_logp = g_logp.unsqueeze(-1)  # [N, 1]
    g_u = g_a * (1.0 - a.square()) + 2.0 * g_logp * a  # [N, A]
    g_log_std = (g_u * std * noise - g_logp) * ((raw >= log_std_min) & (raw <= log_std_max))
    return torch.cat([g_u, g_log_std], dim=-1)
