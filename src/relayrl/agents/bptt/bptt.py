"""Training a policy by backpropagating through Pendulum rollouts (TorchRL's Pendulum tutorial).

The tutorial's recipe, reproduced: an MLP policy (3 hidden layers of 64, Tanh, a linear output
that the env clamps to [-2, 2]), batches of 32 rollouts of 100 steps from random initial
states, loss = -(mean reward over the batch and the rollout), Adam lr 2e-3, gradient norm
clipped to 1.0, 625 iterations (the tutorial's `20_000 // batch_size`), and
`CosineAnnealingLR(optim, 20_000)` stepped once per iteration: with T_max = 20,000 and only
625 steps the learning rate only falls from 2e-3 to 1.995e-3, so the "cosine schedule" is
nearly constant; we keep T_max = 20,000 to reproduce it.

Two ways to get the gradient, equal up to float rounding (tests/test_stateless.py checks it):

- generic (`fast=False`): `rollout()` through `make_pendulum()` with autograd recording
  every op; works for any env and policy.
- fast (`fast=True`, the default): `PendulumMlpRollout`, an autograd.Function that runs the
  policy MLP and the Pendulum dynamics without autograd into preallocated `[T, B, ...]`
  buffers and computes the backward pass by hand: per step only the adjoint recursion
  (three small matmuls and a handful of elementwise ops), with every weight gradient done
  afterwards as one matmul over all T*B rows. On a CPU per-op overhead dominates tensors
  this small, so fewer, larger ops win (bench/stateless_step.py measures both).
  It assumes the Pendulum dynamics of pendulum.py with scalar params and a tanh
  `relayrl.nn.MLP` (`make_policy`); tanh is evaluated as 2 sigmoid(2z) - 1 (cheaper on
  CPU), the same function up to rounding. The MLP's generic hand-written backward
  (relayrl.nn.mlp_fast) does not fit here: this one runs on the sigmoid form, keeps its
  gradients transposed ([hidden, B]) and interleaves them with the dynamics' adjoint.

torch.compile is not used: on a CPU its per-call overhead exceeds what it saves at batch 32,
and its compile time is longer than a whole run.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple, cast

import torch

from relayrl.agents.bptt.config import BpttConfig
from relayrl.envs.stateless.base import make_generator
from relayrl.envs.stateless.pendulum import Pendulum, PendulumParams, make_pendulum
from relayrl.envs.stateless.rollout import rollout
from relayrl.nn import MLP
from relayrl.seeding import RunSeeds


class BpttLog(NamedTuple):
    iteration: int
    mean_reward: float  # over the batch and the rollout: the tutorial's "reward"
    last_reward: float  # mean reward of the rollout's last step: the tutorial's "last reward"
    grad_norm: float  # before clipping
    lr: float


class BpttResult(NamedTuple):
    mean_reward: list[float]  # per iteration
    last_reward: list[float]  # per iteration
    policy: MLP
    seconds: float  # the training loop's wall time

    @property
    def iterations_per_s(self) -> float:
        return len(self.mean_reward) / self.seconds


def make_policy(obs_dim: int = 3, act_dim: int = 1, hidden: Sequence[int] = (64, 64, 64)) -> MLP:
    """The tutorial's MLP: Linear+Tanh per hidden layer, then a linear output."""
    return MLP(obs_dim, list(hidden), act_dim, "tanh")


class _Consts(NamedTuple):
    kg_dt: float  # 3g/(2l) dt
    ku_dt: float  # 3/(m l^2) dt
    dt: float
    max_speed: float
    max_torque: float


def _consts(p: PendulumParams) -> _Consts:
    g, m, l, dt = float(p.g), float(p.m), float(p.l), float(p.dt)  # noqa: E741
    return _Consts(3 * g / (2 * l) * dt, 3.0 / (m * l**2) * dt, dt, float(p.max_speed), float(p.max_torque))


class _Saved(NamedTuple):
    """What the fast forward keeps for its backward, all `[T(+1), B, ...]`."""

    th: torch.Tensor  # [T+1, B]
    obs: torch.Tensor  # [T+1, B, 3]: cos th, sin th, thdot (column 2 is the thdot state)
    sig: list[torch.Tensor]  # per hidden layer [T, B, h]: sigmoid(2 z), so tanh(z) = 2 sig - 1
    a: torch.Tensor  # [T, B, 1] policy output before the clamp
    u: torch.Tensor  # [T, B, 1] torque after the clamp
    pre: torch.Tensor  # [T, B] thdot before the speed clamp


def _sigmoid_weights(ws: Sequence[torch.Tensor], bs: Sequence[torch.Tensor]) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """(W^T, b) per layer for running the MLP on s = sigmoid(2z) instead of h = tanh(z) = 2s - 1:
    sigmoid costs half of tanh on CPU. A hidden layer's sigmoid input is 2z = 2W(2s - 1) + 2b,
    the output layer's a = W(2s - 1) + b."""
    out = []
    for i, (w, b) in enumerate(zip(ws, bs, strict=True)):
        last = i == len(ws) - 1
        k = 1.0 if last else 2.0
        if i == 0:  # the input is the observation itself, not a sigmoid
            out.append(((k * w).t().contiguous(), k * b))
        else:
            out.append(((2 * k * w).t().contiguous(), k * (b - w.sum(1))))
    return out


def _fast_forward(th0: torch.Tensor, thdot0: torch.Tensor, c: _Consts, steps: int,
                   layers: list[tuple[torch.Tensor, torch.Tensor]]) -> _Saved:
    t_max, b = steps, th0.shape[0]
    sv = _Saved(th0.new_empty(t_max + 1, b), th0.new_empty(t_max + 1, b, 3),
                [th0.new_empty(t_max, b, w_t.shape[1]) for w_t, _ in layers[:-1]],
                th0.new_empty(t_max, b, 1), th0.new_empty(t_max, b, 1), th0.new_empty(t_max, b))
    sv.th[0], sv.obs[0, :, 2] = th0, thdot0
    # Per-step views made once (unbind is one call): indexing inside the loop would cost
    # about as much as the arithmetic at these sizes.
    th_v, obs_v, a_v, u_v, u0_v, pre_v = (x.unbind(0) for x in (sv.th, sv.obs, sv.a, sv.u, sv.u[..., 0], sv.pre))
    cos_v, sin_v, td_v = (sv.obs[:, :, i].unbind(0) for i in range(3))
    hidden = [(w_t, bias, s.unbind(0)) for (w_t, bias), s in zip(layers[:-1], sv.sig, strict=True)]
    w_out, b_out = layers[-1]
    for t in range(t_max):
        torch.cos(th_v[t], out=cos_v[t])
        torch.sin(th_v[t], out=sin_v[t])
        x = obs_v[t]  # [B, 3]
        for w_t, bias, s_v in hidden:
            x = torch.addmm(bias, x, w_t, out=s_v[t]).sigmoid_()  # [B, hidden]
        torch.addmm(b_out, x, w_out, out=a_v[t])  # [B, 1]
        torch.clamp(a_v[t], -c.max_torque, c.max_torque, out=u_v[t])
        torch.add(td_v[t], sin_v[t], alpha=c.kg_dt, out=pre_v[t]).add_(u0_v[t], alpha=c.ku_dt)
        torch.clamp(pre_v[t], -c.max_speed, c.max_speed, out=td_v[t + 1])
        torch.add(th_v[t], td_v[t + 1], alpha=c.dt, out=th_v[t + 1])
    return sv


def _state_adjoint_map(g_r: torch.Tensor, sv: _Saved, c: _Consts) -> torch.Tensor:
    """[T, 2, 6, B]: per step, the linear map from the backward's work rows
    (g_pre, g_cos, g_sin, g_thdot_obs, 1, g_th) to (g_th, q) of the step before, where
    q = g_thdot + dt g_th is all the next g_pre needs (thdot' also feeds th' = th + dt thdot')."""
    t_max = g_r.shape[0]
    cos, sin, td = sv.obs[:t_max, :, 0], sv.obs[:t_max, :, 1], sv.obs[:t_max, :, 2]  # [T, B] each
    an = torch.remainder(sv.th[:t_max] + math.pi, 2 * math.pi) - math.pi
    # reward = -(an^2 + 0.1 thdot^2 + 0.001 u^2), so d/d th = -2 an g_r and d/d thdot = -0.2 thdot g_r
    r_th, r_td = g_r * an * -2.0, g_r * td * -0.2
    kc = cos * c.kg_dt  # d pre / d th
    ones, zeros = torch.ones_like(cos), torch.zeros_like(cos)
    to_th = torch.stack([kc, -sin, cos, zeros, r_th, ones], 1)  # [T, 6, B]
    to_q = torch.stack([1 + c.dt * kc, -c.dt * sin, c.dt * cos, ones, r_td + c.dt * r_th, ones * c.dt], 1)
    return torch.stack([to_th, to_q], 1)


def _fast_backward(g_r: torch.Tensor, sv: _Saved, ws: Sequence[torch.Tensor], c: _Consts,
                    ) -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor]]:
    """Adjoint recursion from the last step to the first, with as few small ops per step as
    we could: the MLP's gradients are kept transposed (`[hidden, B]`), and the state adjoint
    is updated by one multiply-and-sum with `_state_adjoint_map` over a packed work buffer."""
    t_max, b = g_r.shape
    a, u = sv.a[..., 0], sv.u[..., 0]
    mask_u = ((a >= -c.max_torque) & (a <= c.max_torque)).to(g_r.dtype)
    mask_v = ((sv.pre >= -c.max_speed) & (sv.pre <= c.max_speed)).to(g_r.dtype)
    r_u = (g_r * u * -0.002 * mask_u).unsqueeze(1).unbind(0)  # d reward / d a, [1, B] per step
    ku, mv = (mask_u * c.ku_dt).unsqueeze(1).unbind(0), mask_v.unbind(0)  # d pre / d a; d thdot' / d pre
    m_v = _state_adjoint_map(g_r, sv, c).unbind(0)
    ds_t = [(4 * s * (1 - s)).transpose(1, 2).contiguous() for s in sv.sig]  # tanh' as [T, h, B]
    top = ds_t[-1] * ws[-1].t()  # [T, h_last, B]: d a / d z_last
    gz_t = [torch.empty_like(d) for d in ds_t]  # d loss / d z, per layer, [T, h, B]
    g_a = g_r.new_empty(t_max, 1, b)
    lower = [(ws[i + 1].t().contiguous(), g_r.new_empty(ds_t[i].shape[1:]), ds_t[i].unbind(0), gz_t[i].unbind(0))
             for i in range(len(ds_t) - 2, -1, -1)]
    top_v, gz_top_v, g_a_v = top.unbind(0), gz_t[-1].unbind(0), g_a.unbind(0)
    w_in_t = ws[0].t().contiguous()
    # work rows: g_pre, g_cos, g_sin, g_thdot_obs, 1, g_th, q (the last two: after step t)
    work = g_r.new_zeros(7, b)
    work[4] = 1.0
    g_pre, g_pre_row, g_obs, inputs, state, q = work[0], work[0:1], work[1:4], work[:6], work[5:7], work[6]
    tmp = g_r.new_empty(2, 6, b)
    for t in range(t_max - 1, -1, -1):
        torch.mul(q, mv[t], out=g_pre)
        ga = torch.addcmul(r_u[t], g_pre_row, ku[t], out=g_a_v[t])  # [1, B]
        g = torch.mul(top_v[t], ga, out=gz_top_v[t])  # [h_last, B]
        for w_t, buf, d_v, gz_v in lower:
            g = torch.mul(torch.mm(w_t, g, out=buf), d_v[t], out=gz_v[t])
        torch.mm(w_in_t, g, out=g_obs)  # [3, B]
        torch.sum(torch.mul(m_v[t], inputs, out=tmp), 1, out=state)  # reads work[5] before overwriting it
    g_th = work[5].clone()
    return g_th, work[6] - c.dt * g_th, [*gz_t, g_a]


class PendulumMlpRollout(torch.autograd.Function):
    """rewards [T, B] of a T-step Pendulum rollout from (th0, thdot0) [B] under the Tanh MLP
    whose weights and biases are `wb` (W1, b1, ..., Wn, bn); gradients by hand (module doc)."""

    @staticmethod
    def forward(ctx: Any, th0: torch.Tensor, thdot0: torch.Tensor, c: _Consts, steps: int,
                *wb: torch.Tensor) -> torch.Tensor:
        sv = _fast_forward(th0, thdot0, c, steps, _sigmoid_weights(wb[0::2], wb[1::2]))
        an = torch.remainder(sv.th[:steps] + math.pi, 2 * math.pi) - math.pi  # [T, B]
        td, u = sv.obs[:steps, :, 2], sv.u[..., 0]
        ctx.save_for_backward(*wb)
        ctx.saved, ctx.c = sv, c
        return -(an * an + 0.1 * td * td + 0.001 * u * u)  # [T, B]

    @staticmethod
    def backward(ctx: Any, g_r: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        ws = ctx.saved_tensors[0::2]
        sv, ctx.saved = ctx.saved, None
        t_max, b = g_r.shape
        g_th, g_td, gz_t = _fast_backward(g_r.contiguous(), sv, ws, ctx.c)
        grads: list[torch.Tensor] = []
        inputs = [sv.obs[:t_max], *(2 * s - 1 for s in sv.sig)]  # each layer's input, [T, B, in]
        for x, g in zip(inputs, gz_t, strict=True):
            g2 = g.transpose(0, 1).reshape(g.shape[1], t_max * b)  # [out, T*B]
            grads += [g2 @ x.reshape(t_max * b, -1), g2.sum(1)]
        return (g_th, g_td, None, None, *grads)


def pendulum_mlp_rewards(policy: MLP, th0: torch.Tensor, thdot0: torch.Tensor, steps: int,
                         params: PendulumParams) -> torch.Tensor:
    """rewards [T, B] of a rollout of `policy` (a make_policy MLP) on Pendulum from th0, thdot0
    [B], differentiable with respect to the policy's parameters and the initial state."""
    linears = list(policy.layers) if isinstance(policy, MLP) and policy.activation == "tanh" else []
    if not linears or linears[0].in_features != 3 or linears[-1].out_features != 1:
        raise ValueError("pendulum_mlp_rewards needs a make_policy(3, 1, hidden) MLP")
    wb = [p for m in linears for p in (m.weight, m.bias)]
    return PendulumMlpRollout.apply(th0, thdot0, _consts(params), steps, *wb)


def train_bptt(config: BpttConfig | None = None, callback: Callable[[BpttLog], None] | None = None, *,
               iterations: int = 625, seed: int = 0, device: str = "cpu", torch_threads: int = 1,
               stop: Callable[[], bool] | None = None, on_start: Callable[[MLP], None] | None = None) -> BpttResult:
    """Train a Pendulum policy by backpropagation through rollouts (see module doc).
    `callback` gets a BpttLog after every iteration (forcing a device sync when given); `on_start`
    the policy network once it is made, before the first iteration (it trains in place after).
    `iterations`: the tutorial's 625 (`20_000 // batch_size`); `torch_threads`: 0 leaves
    torch's setting, 1 is fastest for tensors this small. `stop`, asked after every iteration
    but the last: True ends training there (a Ctrl-C), with the policy trained so far."""
    c = config or BpttConfig()
    threads = torch.get_num_threads()
    if torch_threads > 0:
        torch.set_num_threads(torch_threads)
    try:
        return _train(c, callback, iterations, seed, torch.device(device), stop, on_start)
    finally:
        torch.set_num_threads(threads)


def _train(c: BpttConfig, callback: Callable[[BpttLog], None] | None, iterations: int, seed: int,
           device: torch.device, stop: Callable[[], bool] | None = None,
           on_start: Callable[[MLP], None] | None = None) -> BpttResult:
    env = make_pendulum(device=device)
    params = cast(Pendulum, env.base_env).params  # make_pendulum's base env
    seeds = RunSeeds(seed)
    with torch.random.fork_rng(devices=[]):  # seed the init without touching the caller's RNG
        torch.manual_seed(seeds.base("torch"))
        policy = make_policy(3, 1, c.hidden).to(device)
    gen = make_generator(seeds.base("envs"), "cpu")  # CPU generator: the same initial states on every device
    if on_start is not None:
        on_start(policy)
    optim = torch.optim.Adam(policy.parameters(), lr=c.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(optim, c.lr_t_max)
    stats = torch.empty(iterations, 3, device=device)  # mean, last, grad norm: one sync at the end
    start = time.perf_counter()
    for i in range(iterations):
        state, _ = env.reset((c.batch_size,), gen, device)
        if c.fast:
            rewards = pendulum_mlp_rewards(policy, state.th, state.thdot, c.rollout_steps, params)
        else:
            rewards = rollout(env, policy, c.rollout_steps, state).reward  # [T, B]
        mean = rewards.mean()
        (-mean).backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(policy.parameters(), c.max_grad_norm)
        optim.step()
        optim.zero_grad(set_to_none=True)
        sched.step()
        stats[i] = torch.stack([mean.detach(), rewards[-1].detach().mean(), grad_norm])
        if callback is not None:
            mean_r, last_r, gn = stats[i].tolist()
            callback(BpttLog(i, mean_r, last_r, gn, cast(float, sched.get_last_lr()[0])))  # Adam's lr=c.lr
        if stop is not None and i + 1 < iterations and stop():
            stats = stats[: i + 1]  # the iterations done: the policy is theirs
            break
    values = stats.cpu()  # the sync happens before the clock stops
    seconds = time.perf_counter() - start
    return BpttResult(values[:, 0].tolist(), values[:, 1].tolist(), policy, seconds)
