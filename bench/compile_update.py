"""Does torch.compile make the reference update as fast as the hand-written gradients on a CPU?

    python bench/compile_update.py [--rounds 5] [--steps 300] [--threads 1] [--only dqn sac ppo]
                                   [--dqn-hidden 64,64 256,256]

One gradient step, several ways, timed in the same process round by round (medians; ratios
carry over between machines, absolute times do not):

  hand-written  the agent's `train(batch)` as relayrl runs it (nn/mlp_fast.py + losses_fast.py)
  autograd      the agent's autograd update (`hand_written=False`): its reference on a CPU
  eager         a bare reference: the pure loss (agents/*/losses.py), autograd, torch.optim.Adam
  compiled      the same reference step under torch.compile (inductor, default mode)
  one graph     the reference losses through torch.func.grad_and_value, gradient clipping
                (DQN) and Adam written out, the whole step one torch.compile(fullgraph=True)
                graph (LeanRL's shape, less the CUDA graph); SAC's draws its noise once, so
                it times the maths, not the agent's exact step
  losses compiled  the agent's autograd update with RELAYRL_COMPILE=1 (nn/graphed.py: its loss
                functions through torch.compile, the backward pass and Adam as they are):
                relayrl's own compiled path, which its CUDA graphs capture on a GPU

Settings: DQN with `--dqn-hidden` ReLU layers (64x64 by default; RL Zoo's CartPole network and
dqn-cartpole-fast's are 256x256), batch 64, Huber, grad clip 10; SAC with SB3's Pendulum
defaults (256x256, batch 256, auto entropy); PPO with ppo-stateless-pendulum's (separate 64x64
tanh actor and critic, a minibatch of 2,048, no gradient clip). The compiled columns exclude
compilation (done in warm-up); the compile time is printed on its own, and after the table the
operators one step launches, autograd against losses compiled.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F
from torch.func import functional_call, grad_and_value

from relayrl.agents.dqn import DQNAgent, DQNConfig
from relayrl.agents.dqn.losses import dqn_loss
from relayrl.agents.ppo import PPOAgent, PPOConfig
from relayrl.agents.sac import SACAgent, SACConfig
from relayrl.agents.sac.losses import actor_loss, alpha_loss, critic_loss, critic_targets, tanh_gaussian
from relayrl.envs import make_env
from relayrl.nn import MLP
from relayrl.specs import ArraySpec, DiscreteSpec
from relayrl.types import Batch


def dqn_batch(n: int) -> Batch:
    g = torch.Generator().manual_seed(0)
    obs, next_obs = torch.randn(n, 4, generator=g), torch.randn(n, 4, generator=g)
    return Batch(obs=obs, action=torch.randint(2, (n,), generator=g), reward=torch.randn(n, generator=g),
                 next_obs=next_obs, discount=torch.full((n,), 0.99), weight=None)


def dqn_steps(batch_size: int, hidden: list[int]) -> dict[str, Callable[[], object]]:
    cfg = DQNConfig(hidden=hidden, batch_size=batch_size, lr=2.3e-3, target_update_period=10**9, grad_clip=10.0)
    agent = DQNAgent(ArraySpec((4,), torch.float32), DiscreteSpec(2), cfg, torch.device("cpu"),
                     np.random.default_rng(0))
    batch = dqn_batch(batch_size)
    online, target = MLP(4, hidden, 2, "relu"), MLP(4, hidden, 2, "relu")
    target.load_state_dict(online.state_dict())
    opt = torch.optim.Adam(online.parameters(), lr=2.3e-3)

    def reference() -> torch.Tensor:
        loss, _ = dqn_loss(online, target, batch, double=False, loss="huber")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(online.parameters(), 10.0)
        opt.step()
        return loss.detach()

    def autograd() -> DQNAgent:
        return DQNAgent(ArraySpec((4,), torch.float32), DiscreteSpec(2), cfg, torch.device("cpu"),
                        np.random.default_rng(0), hand_written=False)

    relayrl_eager = autograd()
    with compiled_losses():
        relayrl_compiled = autograd()
    return {"hand-written": lambda: agent.train(batch), "autograd": lambda: relayrl_eager.train(batch),
            "eager": reference, "compiled": torch.compile(reference),
            "one graph": torch.compile(one_graph_dqn_step(online, target, batch), fullgraph=True),
            "losses compiled": lambda: relayrl_compiled.train(batch)}


class compiled_losses:
    """Agents built inside it compile their losses (RELAYRL_COMPILE=1, read when they are built)."""

    def __enter__(self) -> None:
        self.before = os.environ.get("RELAYRL_COMPILE")
        os.environ["RELAYRL_COMPILE"] = "1"

    def __exit__(self, *exc: object) -> None:
        if self.before is None:
            os.environ.pop("RELAYRL_COMPILE", None)
        else:
            os.environ["RELAYRL_COMPILE"] = self.before


def ppo_steps(batch_size: int) -> dict[str, Callable[[], object]]:
    """One minibatch step of ppo-stateless-pendulum's agent: hand-written, autograd, autograd
    with compiled losses."""
    cfg = PPOConfig(hidden=[64, 64], activation="tanh", shared=False, batch_size=batch_size, max_grad_norm=0.0,
                    ent_coef=0.0, gamma=0.9)
    obs_spec = ArraySpec((3,), torch.float32)
    act_spec = ArraySpec((1,), torch.float32, np.full(1, -2.0), np.full(1, 2.0))

    def agent(hand_written: bool) -> PPOAgent:
        return PPOAgent(obs_spec, act_spec, cfg, torch.device("cpu"), np.random.default_rng(0),
                        hand_written=hand_written)

    fast, eager = agent(True), agent(False)
    with compiled_losses():
        relayrl_compiled = agent(False)
    g = torch.Generator().manual_seed(0)
    n = batch_size
    minibatch = (torch.randn(n, 3, generator=g), torch.randn(n, 1, generator=g), *torch.randn(4, n, generator=g))
    return {"hand-written": lambda: fast.update(*minibatch, 0.2), "autograd": lambda: eager.update(*minibatch, 0.2),
            "losses compiled": lambda: relayrl_compiled.update(*minibatch, 0.2)}


def one_graph_dqn_step(online: MLP, target: MLP, batch: Batch) -> Callable[[], torch.Tensor]:
    """The reference DQN step as one function of tensors: gradients by torch.func, then
    clipping to norm 10 and Adam (lr 2.3e-3) in place, so nothing breaks the graph."""
    params = {k: v.detach().clone() for k, v in online.named_parameters()}
    target_params = {k: v.detach().clone() for k, v in target.named_parameters()}
    adam = InPlaceAdam(params, 2.3e-3)

    def loss_fn(p: dict[str, torch.Tensor]) -> torch.Tensor:
        loss, _ = dqn_loss(lambda x: functional_call(online, p, (x,)),
                           lambda x: functional_call(target, target_params, (x,)), batch, double=False)
        return loss

    grad_fn = grad_and_value(loss_fn)

    def step() -> torch.Tensor:
        grads, loss = grad_fn(params)
        norm = torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in grads.values()]))
        scale = (10.0 / (norm + 1e-6)).clamp(max=1.0)
        adam.step({k: g * scale for k, g in grads.items()})
        return loss

    return step


class InPlaceAdam:
    """Adam (no weight decay) written out in tensor ops, so a compiled graph holds it."""

    def __init__(self, params: dict[str, torch.Tensor], lr: float) -> None:
        self.params, self.lr = params, lr
        self.m1 = {k: torch.zeros_like(v) for k, v in params.items()}
        self.m2 = {k: torch.zeros_like(v) for k, v in params.items()}
        self.count = torch.zeros(())

    def step(self, grads: dict[str, torch.Tensor]) -> None:
        self.count.add_(1)
        c1, c2 = 1 - 0.9 ** self.count, 1 - 0.999 ** self.count
        for k, p in self.params.items():
            g = grads[k]
            self.m1[k].lerp_(g, 0.1)
            self.m2[k].mul_(0.999).addcmul_(g, g, value=0.001)
            p.sub_(self.lr * (self.m1[k] / c1) / ((self.m2[k] / c2).sqrt() + 1e-8))


def sac_steps(batch_size: int) -> dict[str, Callable[[], object]]:
    env = make_env("Pendulum-v1", 1)
    obs_spec, act_spec = env.observation_spec, env.action_spec
    env.close()
    cfg = SACConfig(batch_size=batch_size)
    agent = SACAgent(obs_spec, act_spec, cfg, torch.device("cpu"), np.random.default_rng(0))
    g = torch.Generator().manual_seed(0)
    n, o, a = batch_size, obs_spec.shape[0], act_spec.shape[0]
    batch = Batch(obs=torch.randn(n, o, generator=g), action=torch.rand(n, a, generator=g) * 2 - 1,
                  reward=torch.randn(n, generator=g), next_obs=torch.randn(n, o, generator=g),
                  discount=torch.full((n,), 0.99), weight=None)
    actor = MLP(o, [256, 256], 2 * a, "relu")
    critics = [MLP(o + a, [256, 256], 1, "relu") for _ in range(2)]
    targets = [MLP(o + a, [256, 256], 1, "relu") for _ in range(2)]
    for t, c in zip(targets, critics, strict=True):
        t.load_state_dict(c.state_dict())
    log_alpha = torch.zeros((), requires_grad=True)
    actor_opt = torch.optim.Adam(actor.parameters(), lr=3e-4)
    critic_opt = torch.optim.Adam([p for c in critics for p in c.parameters()], lr=3e-4)
    alpha_opt = torch.optim.Adam([log_alpha], lr=3e-4)

    def policy(obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, log_std = actor(obs).chunk(2, dim=-1)
        return tanh_gaussian(mean, log_std.clamp(-20, 2), torch.randn_like(mean))

    def q(nets: list[MLP], obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        x = torch.cat([obs, act], dim=-1)
        return torch.stack([net(x).squeeze(-1) for net in nets])  # [2, N]

    def reference() -> torch.Tensor:
        alpha = log_alpha.exp().detach()
        with torch.no_grad():
            next_a, next_logp = policy(batch.next_obs)
            y = critic_targets(batch.reward, batch.discount, q(targets, batch.next_obs, next_a), next_logp, alpha, 1.0)
        c_loss, _ = critic_loss(q(critics, batch.obs, batch.action), y)
        critic_opt.zero_grad(set_to_none=True)
        c_loss.backward()
        critic_opt.step()
        act, logp = policy(batch.obs)
        a_loss = actor_loss(logp, q(critics, batch.obs, act), alpha)
        actor_opt.zero_grad(set_to_none=True)
        a_loss.backward()
        actor_opt.step()
        al = alpha_loss(log_alpha, logp, -float(a))
        alpha_opt.zero_grad(set_to_none=True)
        al.backward()
        alpha_opt.step()
        with torch.no_grad():
            for t, c in zip(targets, critics, strict=True):
                for pt, pc in zip(t.parameters(), c.parameters(), strict=True):
                    pt.lerp_(pc, 0.005)
        return F.relu(c_loss.detach())

    one = one_graph_sac_step(actor, critics, targets, batch, -float(a))
    relayrl_eager = SACAgent(obs_spec, act_spec, cfg, torch.device("cpu"), np.random.default_rng(0),
                             hand_written=False)
    with compiled_losses():
        relayrl_compiled = SACAgent(obs_spec, act_spec, cfg, torch.device("cpu"), np.random.default_rng(0),
                                    hand_written=False)
    return {"hand-written": lambda: agent.train(batch), "autograd": lambda: relayrl_eager.train(batch),
            "eager": reference, "compiled": torch.compile(reference),
            "one graph": torch.compile(one, fullgraph=True), "losses compiled": lambda: relayrl_compiled.train(batch)}


def one_graph_sac_step(actor: MLP, critics: list[MLP], targets: list[MLP], batch: Batch,
                       target_entropy: float) -> Callable[[], torch.Tensor]:
    """The reference SAC step (critic, actor, temperature, Polyak) as one function of tensors:
    gradients by torch.func, Adam (lr 3e-4) in place."""
    actor_p = {k: v.detach().clone() for k, v in actor.named_parameters()}
    critic_p = {f"{i}.{k}": v.detach().clone() for i, c in enumerate(critics) for k, v in c.named_parameters()}
    target_p = {k: v.clone() for k, v in critic_p.items()}
    log_alpha = {"log_alpha": torch.zeros(())}
    adams = [InPlaceAdam(d, 3e-4) for d in (critic_p, actor_p, log_alpha)]
    g = torch.Generator().manual_seed(0)
    noise = torch.randn(2, batch.obs.shape[0], batch.action.shape[1], generator=g)

    def policy(p: dict[str, torch.Tensor], obs: torch.Tensor, eps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, log_std = functional_call(actor, p, (obs,)).chunk(2, dim=-1)
        return tanh_gaussian(mean, log_std.clamp(-20, 2), eps)

    def q(p: dict[str, torch.Tensor], obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        x = torch.cat([obs, act], dim=-1)
        return torch.stack([functional_call(critics[i], {k.split(".", 1)[1]: v for k, v in p.items()
                                                        if k.startswith(f"{i}.")}, (x,)).squeeze(-1)
                            for i in range(2)])  # [2, N]

    def critic_fn(p: dict[str, torch.Tensor], y: torch.Tensor) -> torch.Tensor:
        return critic_loss(q(p, batch.obs, batch.action), y)[0]

    def actor_fn(p: dict[str, torch.Tensor], alpha: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        act, logp = policy(p, batch.obs, noise[1])
        return actor_loss(logp, q(critic_p, batch.obs, act), alpha), logp.detach()

    def alpha_fn(p: dict[str, torch.Tensor], logp: torch.Tensor) -> torch.Tensor:
        return alpha_loss(p["log_alpha"], logp, target_entropy)

    critic_grad, actor_grad, alpha_grad = (grad_and_value(critic_fn), grad_and_value(actor_fn, has_aux=True),
                                           grad_and_value(alpha_fn))

    def step() -> torch.Tensor:
        alpha = log_alpha["log_alpha"].exp()
        next_a, next_logp = policy(actor_p, batch.next_obs, noise[0])
        y = critic_targets(batch.reward, batch.discount, q(target_p, batch.next_obs, next_a), next_logp, alpha, 1.0)
        grads, c_loss = critic_grad(critic_p, y)
        adams[0].step(grads)
        grads, (_, logp) = actor_grad(actor_p, alpha)
        adams[1].step(grads)
        grads, _ = alpha_grad(log_alpha, logp)
        adams[2].step(grads)
        for k, t in target_p.items():
            t.lerp_(critic_p[k], 0.005)
        return c_loss

    return step


def top_level_ops(fn: Callable[[], object]) -> int:
    """Operators one step launches, as torch.profiler sees them at the top level (on a GPU,
    about the kernels a CUDA graph of the step holds)."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        fn()
    return sum(1 for e in prof.events() if e.cpu_parent is None)


def per_step_us(fn: Callable[[], object], steps: int) -> float:
    t0 = time.perf_counter()
    for _ in range(steps):
        fn()
    return (time.perf_counter() - t0) / steps * 1e6


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--only", nargs="+", choices=["dqn", "sac", "ppo"], default=["dqn", "sac", "ppo"])
    p.add_argument("--dqn-hidden", nargs="+", default=["64,64"],
                   help="DQN hidden sizes to time, e.g. 64,64 256,256 (RL Zoo's CartPole, dqn-cartpole-fast)")
    args = p.parse_args()
    torch.set_flush_denormal(True)  # as a run does (training/lifecycle.py)
    torch.set_num_threads(args.threads)
    work: list[tuple[str, Callable[[], dict[str, Callable[[], object]]]]] = []
    for name in args.only:
        if name == "dqn":
            for h in args.dqn_hidden:
                sizes = [int(x) for x in h.split(",")]
                work.append((f"dqn {tuple(sizes)} (batch 64)", lambda sizes=sizes: dqn_steps(64, sizes)))
        elif name == "sac":
            work.append(("sac (256, 256) (batch 256)", lambda: sac_steps(256)))
        else:
            work.append(("ppo (64, 64) tanh (minibatch 2,048)", lambda: ppo_steps(2048)))
    columns = ("hand-written", "autograd", "eager", "compiled", "one graph", "losses compiled")
    ops: list[str] = []
    print(f"torch {torch.__version__}, {args.threads} thread(s), medians of {args.rounds} rounds x {args.steps} steps")
    print("| update | " + " | ".join(f"{c} us" for c in columns) + " | best compiled / hand-written | compile s |")
    print("|---|" + "---|" * (len(columns) + 2))
    for name, make in work:
        steps = make()
        t0 = time.perf_counter()
        for key in ("compiled", "one graph", "losses compiled"):
            for _ in range(3 if key in steps else 0):
                steps[key]()
        compile_s = time.perf_counter() - t0
        for fn in steps.values():
            per_step_us(fn, 20)  # warm-up
        times: dict[str, list[float]] = {k: [] for k in steps}
        for _ in range(args.rounds):
            for k, fn in steps.items():
                times[k].append(per_step_us(fn, args.steps))
        med = {k: statistics.median(v) for k, v in times.items()}
        best = min(v for k, v in med.items() if k not in ("hand-written", "autograd", "eager"))
        cells = " | ".join(f"{med[c]:.0f}" if c in med else "-" for c in columns)
        print(f"| {name} | {cells} | {best / med['hand-written']:.2f} | {compile_s:.1f} |")
        ops.append(f"{name}: autograd {top_level_ops(steps['autograd'])}, "
                   f"losses compiled {top_level_ops(steps['losses compiled'])}")
    print("\noperators per step (torch.profiler, top level):\n" + "\n".join(ops))


if __name__ == "__main__":
    main()
