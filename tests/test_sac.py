"""SAC: losses against hand-computed values, the tanh-Gaussian log-prob, the twin critic,
target updates, determinism, export and a short learning test."""

import math

import numpy as np
import pytest
import torch
from torch.distributions import Normal, TanhTransform, TransformedDistribution

import relayrl
from relayrl.agents.sac import SACAgent, SACConfig, actor_loss, alpha_loss, critic_loss, critic_targets, tanh_gaussian
from relayrl.errors import UserError
from relayrl.specs import ArraySpec, DiscreteSpec
from relayrl.types import Batch

OBS = ArraySpec((3,), torch.float32, -np.ones(3), np.ones(3))
ACT = ArraySpec((2,), torch.float32, np.array([-2.0, 0.0]), np.array([2.0, 1.0]))


def agent(seed=0, **kw):
    cfg = SACConfig(actor_hidden=[16], critic_hidden=[16, 16], batch_size=8, **kw)
    torch.manual_seed(seed)
    return SACAgent(OBS, ACT, cfg, torch.device("cpu"), np.random.default_rng(seed))


def batch(n=8, seed=0):
    g = torch.Generator().manual_seed(seed)
    action = torch.stack([torch.rand(n, generator=g) * 4 - 2, torch.rand(n, generator=g)], dim=1)
    return Batch(torch.randn(n, 3, generator=g), action, torch.randn(n, generator=g),
                 torch.randn(n, 3, generator=g), torch.full((n,), 0.99), None)


def test_tanh_gaussian_log_prob_matches_torch_distributions():
    mean = torch.tensor([[0.3, -1.2], [2.5, 0.0]])
    log_std = torch.tensor([[-0.5, 0.2], [0.1, -2.0]])
    noise = torch.tensor([[0.7, -0.4], [1.5, 3.0]])
    a, logp = tanh_gaussian(mean, log_std, noise)
    ref = TransformedDistribution(Normal(mean, log_std.exp()), [TanhTransform()])
    assert torch.allclose(a, torch.tanh(mean + log_std.exp() * noise))
    assert torch.allclose(logp, ref.log_prob(a).sum(-1), atol=1e-4)


def test_tanh_gaussian_log_prob_stays_finite_where_tanh_saturates():
    _, logp = tanh_gaussian(torch.tensor([[30.0]]), torch.tensor([[0.0]]), torch.tensor([[0.0]]))
    # log N(0) - log(1 - tanh(30)^2) = -0.919 - 2 (log 2 - 30 - softplus(-60)) = 57.69;
    # computing log(1 - tanh(30)^2) directly would give log(0) = -inf.
    expected = -0.5 * math.log(2 * math.pi) - 2 * (math.log(2.0) - 30.0)
    assert math.isfinite(float(logp)) and float(logp) == pytest.approx(expected, rel=1e-5)


def test_critic_targets_take_the_min_and_subtract_entropy_without_bootstrapping_terminals():
    next_q = torch.tensor([[5.0, 1.0], [3.0, 4.0]])  # [2 critics, N=2]
    y = critic_targets(torch.tensor([1.0, 2.0]), torch.tensor([0.9, 0.0]), next_q,
                       torch.tensor([-1.0, 0.5]), alpha=0.2, reward_scale=2.0)
    # 2*1 + 0.9*(min(5,3) - 0.2*-1) = 2 + 0.9*3.2 = 4.88; terminated: 2*2 = 4
    assert torch.allclose(y, torch.tensor([4.88, 4.0]))


def test_critic_loss_is_half_mean_squared_error_summed_over_critics():
    q = torch.tensor([[1.0, 2.0], [3.0, 0.0]], requires_grad=True)
    loss, td = critic_loss(q, torch.tensor([1.0, 1.0]))
    assert loss.item() == pytest.approx(0.5 * (0.5 + 2.5))  # td [[0, 1], [2, -1]]
    assert torch.equal(td, torch.tensor([0.0, 1.0]))
    weighted, _ = critic_loss(q, torch.tensor([1.0, 1.0]), torch.tensor([1.0, 0.0]))
    assert weighted.item() == pytest.approx(0.5 * (0.0 + 2.0))  # only sample 0 counts


def test_actor_and_alpha_losses():
    q_pi = torch.tensor([[1.0, 3.0], [2.0, 0.0]])
    # 0.5*-1 - min(1,2) = -1.5; 0.5*2 - min(3,0) = 1 -> mean -0.25
    assert float(actor_loss(torch.tensor([-1.0, 2.0]), q_pi, 0.5)) == pytest.approx(-0.25)
    log_alpha = torch.tensor(math.log(2.0), requires_grad=True)
    loss = alpha_loss(log_alpha, torch.tensor([1.0, 3.0]), target_entropy=-1.0)
    assert loss.item() == pytest.approx(-math.log(2.0) * 1.0)  # mean(1 - 1, 3 - 1) = 1
    loss.backward()  # entropy -2 is below the target -1: alpha must grow, i.e. gradient < 0
    assert float(log_alpha.grad) == pytest.approx(-1.0)


def test_target_critics_follow_by_polyak_averaging():
    ag = agent(tau=0.25)
    before = [p.detach().clone() for p in ag.target_critic.parameters()]
    ag.train(batch())
    for old, new, online in zip(before, ag.target_critic.parameters(), ag.critic.parameters(), strict=True):
        assert torch.allclose(new, 0.75 * old + 0.25 * online.detach(), atol=1e-6)


def test_target_update_period_skips_steps():
    ag = agent(tau=0.5, target_update_period=2)
    before = [p.detach().clone() for p in ag.target_critic.parameters()]
    ag.train(batch())
    assert all(torch.equal(a, b) for a, b in zip(before, ag.target_critic.parameters(), strict=True))
    ag.train(batch(seed=1))
    assert not all(torch.equal(a, b) for a, b in zip(before, ag.target_critic.parameters(), strict=True))


def test_alpha_is_fixed_without_autotuning_and_moves_with_it():
    fixed, tuned = agent(autotune_alpha=False, init_alpha=0.3), agent(init_alpha=0.3)
    for a in (fixed, tuned):
        a.train(batch())
    assert fixed.alpha == pytest.approx(0.3) and tuned.alpha != pytest.approx(0.3)


def test_same_seed_same_updates_and_state_round_trip():
    a, b = agent(seed=3), agent(seed=3)
    for i in range(3):
        ma, mb = a.train(batch(seed=i)), b.train(batch(seed=i))
        assert torch.equal(ma["critic_loss"], mb["critic_loss"])
    c = agent(seed=9)
    c.load_state_dict(a.state_dict())
    ma, mc = a.train(batch(seed=7)), c.train(batch(seed=7))
    assert torch.equal(ma["actor_loss"], mc["actor_loss"]) and torch.equal(ma["critic_loss"], mc["critic_loss"])


def test_policies_respect_action_bounds_at_any_batch_size():
    ag = agent()
    for b in (1, 7):
        for policy in (ag.collect_policy(), ag.eval_policy()):
            a = policy(torch.randn(b, 3) * 10)
            assert a.shape == (b, 2) and a.dtype == torch.float32
            low, high = torch.tensor([-2.0, 0.0]), torch.tensor([2.0, 1.0])
            assert bool(((a >= low) & (a <= high)).all())
    obs = torch.randn(5, 3)
    assert torch.equal(ag.eval_policy()(obs), ag.eval_policy()(obs))
    assert not torch.equal(ag.collect_policy()(obs), ag.collect_policy()(obs))


def test_saturated_actions_stay_inside_bounds_that_float32_rounds_past():
    """loc - half is 0.099999994 for Box(0.1, 0.3) in float32: a saturated tanh must give the bound,
    in the collect, eval and on-device policies and in the exported module."""
    from relayrl.agents.sac.policy import TanhMean

    act = ArraySpec((1,), torch.float32, np.array([0.1], np.float32), np.array([0.3], np.float32))
    torch.manual_seed(0)
    ag = SACAgent(OBS, act, SACConfig(actor_hidden=[16], critic_hidden=[16]), torch.device("cpu"),
                  np.random.default_rng(0))
    obs = torch.randn(256, 3) * 1e6  # tanh saturates at +-1 both ways
    low, high = np.float32(0.1), np.float32(0.3)
    policies = [ag.collect_policy(), ag.eval_policy()]
    outs = [p(obs) for p in policies] + [policies[1].act_on_device(obs)]
    with torch.no_grad():
        outs.append(TanhMean(ag.policy_state())(obs))
    for a in outs:
        assert float(a.min()) == low and float(a.max()) == high


def test_sac_refuses_discrete_actions():
    with pytest.raises(UserError, match="SAC takes a Box action space of floats with finite low and high"):
        SACAgent(OBS, DiscreteSpec(2), SACConfig(), torch.device("cpu"), np.random.default_rng(0))


REACH = ["env.id=toy_envs:Reach", "train.total_steps=1500", "train.initial_collect_steps=200",
         "eval.interval=500", "eval.episodes=20", "agent.actor_hidden=[64,64]", "agent.critic_hidden=[64,64]",
         "agent.batch_size=64", "agent.actor_lr=3e-3", "agent.critic_lr=3e-3", "agent.alpha_lr=3e-3",
         "train.torch_threads=1"]


def test_sac_learns_a_continuous_one_step_task(tmp_path):
    config = relayrl.load_config("sac-pendulum", REACH, seed=0)
    result = relayrl.train(config, tmp_path / "run", progress=False)
    # a random policy averages about -2.8; the optimum is 0
    assert result.final["average_return"] > -0.15, result.final


def test_saved_policy_samples_when_asked(tmp_path):  # load and export round trips: tests/test_conformance.py
    config = relayrl.load_config("sac-pendulum", REACH + ["train.total_steps=300"], seed=1)
    relayrl.train(config, tmp_path / "run", progress=False)
    obs = torch.rand(7, 2) * 2 - 1
    live = relayrl.load_policy(tmp_path / "run")(obs)
    assert live.shape == (7, 2)
    sampled = relayrl.load_policy(tmp_path / "run", deterministic=False, seed=0)
    assert not torch.equal(sampled(obs), live)


def test_sac_run_is_deterministic_and_resumes(tmp_path):
    short = REACH + ["train.total_steps=400", "train.initial_collect_steps=100", "eval.interval=200",
                     "train.checkpoint_interval=200", "agent.actor_hidden=[16]", "agent.critic_hidden=[16]"]
    for name in ("a", "b"):
        relayrl.train(relayrl.load_config("sac-pendulum", short, seed=2), tmp_path / name, progress=False)
    a, b = (relayrl.training.run_dir.RunDir(tmp_path / n).read_metrics() for n in ("a", "b"))
    assert [(r["average_return"], r.get("losses/critic_loss")) for r in a] == \
           [(r["average_return"], r.get("losses/critic_loss")) for r in b]
    assert a[-1]["losses/critic_loss"] > 0
    longer = relayrl.load_config("sac-pendulum", short + ["train.total_steps=600"], seed=2)
    result = relayrl.train(longer, tmp_path / "a", resume=True, progress=False)
    steps = [r["step"] for r in relayrl.training.run_dir.RunDir(tmp_path / "a").read_metrics()]
    assert steps == [0, 200, 400, 600] and result.final["train_step"] > a[-1]["train_step"]
