"""PPO: losses against hand-computed values, GAE against a brute-force reference, the rollout
queue, short learning runs (discrete and continuous), sync = async, the saved policy.
Load / export / resume round trips: tests/test_conformance.py; the preset: test_presets_learn.py."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from test_resume import assert_same_state, comparable, cut_back

import relayrl
from relayrl.agents.ppo.advantages import gae
from relayrl.agents.ppo.agent import PPOAgent
from relayrl.agents.ppo.config import PPOConfig
from relayrl.agents.ppo.distributions import log_prob_entropy
from relayrl.agents.ppo.losses import explained_variance, normalize, policy_loss, value_loss
from relayrl.errors import ConfigError, UserError
from relayrl.policy_file import load_policy_file
from relayrl.replay import Table
from relayrl.replay.rollouts import RolloutWriter
from relayrl.specs import ArraySpec, DiscreteSpec
from relayrl.training.run_dir import RunDir
from relayrl.types import Transition


def test_clipped_surrogate_by_hand():
    adv = torch.tensor([1.0, -1.0, 2.0, -2.0])
    ratio = torch.tensor([1.5, 1.5, 0.5, 0.5])  # clip 0.2: 1.2, 1.2, 0.8, 0.8
    old = torch.zeros(4)
    loss, kl, frac = policy_loss(ratio.log(), old, adv, 0.2)
    # min(r A, clip(r) A): min(1.5, 1.2)=1.2; min(-1.5, -1.2)=-1.5; min(1.0, 1.6)=1.0; min(-1.0, -1.6)=-1.6
    assert loss.item() == pytest.approx(-(1.2 - 1.5 + 1.0 - 1.6) / 4)
    assert frac.item() == 1.0
    expected_kl = np.mean([(r - 1) - math.log(r) for r in (1.5, 1.5, 0.5, 0.5)])
    assert kl.item() == pytest.approx(expected_kl)
    loss, kl, frac = policy_loss(old, old, adv, 0.2)  # ratio 1: the loss is -mean(A)
    assert loss.item() == pytest.approx(0.0) and kl.item() == 0.0 and frac.item() == 0.0


def test_value_loss_by_hand_with_and_without_clipping():
    v, old, ret = torch.tensor([1.0, 0.0]), torch.tensor([0.0, 0.0]), torch.tensor([2.0, 1.0])
    assert value_loss(v, old, ret).item() == pytest.approx((1.0 + 1.0) / 2)
    # clip 0.5: v_clipped = [0.5, 0.0]; max((1-2)^2, (0.5-2)^2) = 2.25, max(1, 1) = 1
    assert value_loss(v, old, ret, 0.5).item() == pytest.approx((2.25 + 1.0) / 2)


def test_clip_range_vf_says_it_is_ppo2s_max_not_sb3s_clipped_error():
    # The key's meaning read "clip the value prediction", SB3's form, where the loss takes the max (PPO2's).
    from relayrl.agents.ppo.config import PPOConfig
    from relayrl.config_fields import meanings

    meaning = meanings(PPOConfig)["clip_range_vf"]
    assert "the larger of the squared errors" in meaning and "SB3's clip_range_vf takes the clipped one only" in meaning


def test_normalize_and_explained_variance():
    a = torch.tensor([1.0, 2.0, 3.0])
    assert torch.allclose(normalize(a), torch.tensor([-1.0, 0.0, 1.0]), atol=1e-6)
    assert torch.equal(normalize(torch.tensor([5.0])), torch.tensor([5.0]))
    r = torch.tensor([1.0, 2.0, 3.0, 4.0])
    assert explained_variance(r, r).item() == 1.0
    assert explained_variance(torch.full((4,), 2.5), r).item() == pytest.approx(0.0)


def test_log_probs_and_entropies_match_torch_distributions():
    torch.manual_seed(0)
    logits, a = torch.randn(5, 3), torch.randint(0, 3, (5,))
    logp, ent = log_prob_entropy(logits, None, a)
    d = torch.distributions.Categorical(logits=logits)
    assert torch.allclose(logp, d.log_prob(a)) and torch.allclose(ent, d.entropy())
    mean, log_std, x = torch.randn(5, 2), torch.tensor([-0.3, 0.4]), torch.randn(5, 2)
    logp, ent = log_prob_entropy(mean, log_std, x)
    n = torch.distributions.Normal(mean, log_std.exp())
    assert torch.allclose(logp, n.log_prob(x).sum(-1), atol=1e-6)
    assert torch.allclose(ent, n.entropy().sum(-1), atol=1e-6)


def brute_force_gae(r, v, nv, term, trunc, gamma, lam):
    """A_t = sum_k (gamma lam)^k delta_{t+k}, the sum stopping at the episode's end."""
    t_len, b = r.shape
    adv = np.zeros((t_len, b))
    for j in range(b):
        for t in range(t_len):
            total, w = 0.0, 1.0
            for k in range(t, t_len):
                delta = r[k, j] + gamma * (0.0 if term[k, j] else nv[k, j]) - v[k, j]
                total += w * delta
                if term[k, j] or trunc[k, j]:
                    break
                w *= gamma * lam
            adv[t, j] = total
    return adv


@pytest.mark.parametrize("lam", [0.0, 0.8, 1.0])
def test_gae_matches_a_brute_force_reference_over_terminations_and_truncations(lam):
    rng = np.random.default_rng(1)
    t_len, b = 9, 4
    r, v, nv = (rng.normal(size=(t_len, b)) for _ in range(3))
    term = rng.random((t_len, b)) < 0.2
    trunc = (rng.random((t_len, b)) < 0.2) & ~term
    term[-1, 0], trunc[-1, 1] = True, True  # episode ends on the rollout's last step too
    adv, ret = gae(*(torch.tensor(x) for x in (r, v, nv, term, trunc)), 0.98, lam)
    expected = brute_force_gae(r, v, nv, term, trunc, 0.98, lam)
    assert np.allclose(adv.numpy(), expected) and np.allclose(ret.numpy(), expected + v)


def test_gae_bootstraps_truncation_from_the_true_final_value_and_not_termination():
    r, v = torch.zeros(1, 2), torch.zeros(1, 2)
    nv = torch.tensor([[10.0, 10.0]])  # V of the true final observations
    adv, _ = gae(r, v, nv, torch.tensor([[True, False]]), torch.tensor([[False, True]]), 0.5, 0.9)
    assert adv.tolist() == [[0.0, 5.0]]


def step(obs, t):
    return Transition(torch.full((2, 3), float(t)), torch.tensor([t, t]), torch.ones(2), torch.zeros(2, 3),
                      torch.zeros(2, dtype=torch.bool), torch.zeros(2, dtype=torch.bool))


def test_rollout_writer_inserts_one_item_per_rollout_consumed_once():
    table = Table.queue("rollouts", 1)
    w = RolloutWriter(table, steps=3)
    for t in range(3):
        assert table.samples_available() == 0
        w(step(None, t))
    assert table.samples_available() == 1 and w.pending() == 0
    item, _ = table.sample(1)
    assert item["obs"].shape == (1, 3, 2, 3) and item["action"][0, :, 0].tolist() == [0, 1, 2]
    assert table.samples_available() == 0 and table.size == 0


def agent(action_spec, **kw):
    cfg = PPOConfig(hidden=[8], batch_size=4, n_epochs=2, **kw)
    return PPOAgent(ArraySpec((3,), torch.float32), action_spec, cfg, torch.device("cpu"),
                    np.random.default_rng(0), total_steps=100)


def rollout(action):
    g = torch.Generator().manual_seed(0)
    t, b = 4, 2
    return {"obs": torch.randn(1, t, b, 3, generator=g), "action": action, "reward": torch.randn(1, t, b, generator=g),
            "next_obs": torch.randn(1, t, b, 3, generator=g), "terminated": torch.zeros(1, t, b, dtype=torch.bool),
            "truncated": torch.zeros(1, t, b, dtype=torch.bool)}


@pytest.mark.parametrize("shared", [False, True])
def test_train_counts_minibatches_reports_scalars_and_follows_the_schedules(shared):
    a = agent(DiscreteSpec(3), shared=shared, lr=1e-3, lr_end=0.0, clip_range=0.2, clip_range_end=0.0)
    a.set_progress(50)
    assert a.opt.lr == pytest.approx(5e-4) and a.clip_range == pytest.approx(0.1)
    before = [p.clone() for p in a.net.parameters()]
    m = a.train(rollout(torch.randint(0, 3, (1, 4, 2))))
    assert a.train_step == 2 * 2  # 2 epochs of 8 steps in minibatches of 4
    for k in ("policy_loss", "value_loss", "entropy", "approx_kl", "clip_fraction", "explained_variance"):
        assert torch.isfinite(m[k]), k
    assert all(not torch.equal(p, q) for p, q in zip(before, a.net.parameters(), strict=True))


def test_shared_network_saves_a_plain_actor_mlp():
    a = agent(DiscreteSpec(3), shared=True)
    state = a.policy_state()
    assert state["state_dict"]["layers.1.weight"].shape == (3, 8)
    obs = torch.randn(5, 3)
    net = relayrl.agents.ppo.policy.deterministic_module(state)
    assert torch.equal(net(obs), a.eval_policy()(obs))


def test_continuous_actions_are_clipped_and_the_mean_is_deterministic():
    spec = ArraySpec((2,), torch.float32, np.array([-0.1, -1.0], np.float32), np.array([0.1, 1.0], np.float32))
    a = agent(spec, log_std_init=2.0)
    obs = torch.randn(64, 3)
    policy = a.collect_policy()
    act = policy.env_action(policy(obs))  # what the env receives (the rollout keeps the sample itself)
    assert act.shape == (64, 2) and (act[:, 0].abs() <= 0.1).all() and (act[:, 1].abs() <= 1.0).all()
    assert (act[:, 1].abs() == 1.0).any()  # std e^2: many draws land beyond the bounds
    assert torch.equal(a.eval_policy()(obs), a.eval_policy()(obs))
    a.train(rollout(torch.randn(1, 4, 2, 2)))


def test_discrete_samples_follow_the_logits():
    a = agent(DiscreteSpec(2))
    with torch.no_grad():
        a.net.policy.mlp.layers[-1].bias.copy_(torch.tensor([0.0, math.log(3.0)]))
        a.net.policy.mlp.layers[-1].weight.zero_()
    acts = a.collect_policy()(torch.zeros(4000, 3))
    assert acts.float().mean().item() == pytest.approx(0.75, abs=0.03)


def test_refuses_a_box_without_bounds_random_warmup_and_stale_actors(tmp_path):
    with pytest.raises(UserError, match="PPO takes"):
        agent(ArraySpec((2,), torch.float32))  # infinite bounds are taken: tests/test_spaces.py
    for key in ("initial_collect_steps", "pull_interval", "gradient_steps"):
        with pytest.raises(ConfigError, match=key):
            relayrl.load_config("ppo-cartpole", [f"train.{key}=100"])
        cfg = relayrl.load_config("ppo-cartpole")
        setattr(cfg.train, key, 100)  # set in Python after loading: train() checks it too
        with pytest.raises(ConfigError, match=key):
            relayrl.train(cfg, tmp_path / key, progress=False)
    relayrl.load_config("ppo-cartpole", ["train.gradient_steps=0"])  # collection only (bench/ppo_stateless.py)


def test_refuses_a_minibatch_larger_than_a_rollout():
    rollout = relayrl.load_config("ppo-cartpole").train.collect_steps
    relayrl.load_config("ppo-cartpole", [f"agent.batch_size={rollout}"])  # the whole rollout: taken
    with pytest.raises(ConfigError, match=r"agent.batch_size=\d+ is more than one rollout \(\d+ env steps"):
        relayrl.load_config("ppo-cartpole", [f"agent.batch_size={rollout + 1}"])
    # 10 steps over 4 copies is a rollout of 12
    relayrl.load_config("ppo-cartpole", ["env.num_envs=4", "train.collect_steps=10", "agent.batch_size=12"])


def test_a_batch_size_that_does_not_divide_the_rollout_is_said_at_the_start(tmp_path, capsys):
    # 3 copies x 43 steps = 129: minibatches of 64, 64 and 1, whose one step took an Adam step unsaid.
    over = ["env.num_envs=3", "train.collect_steps=128", "train.total_steps=129", "eval.interval=0"]
    relayrl.train(relayrl.load_config("ppo", over), tmp_path / "r", progress=False)
    assert ("agent.batch_size=64 does not divide a rollout of 129 env steps (train.collect_steps in whole batched "
            "steps of env.num_envs=3): each epoch ends with a minibatch of 1") in capsys.readouterr().err
    relayrl.train(relayrl.load_config("ppo", over[:3] + ["agent.batch_size=43", "eval.interval=0"]), tmp_path / "s",
                  progress=False)
    assert "does not divide" not in capsys.readouterr().err


def test_a_total_that_ends_in_a_partial_rollout_is_said_at_the_start(tmp_path, capsys):
    """SB3's learn(6000) with rollouts of 1024 trains on 6 (to 6,144 steps); here the run ends at
    6,000 and its last 880 steps, collected, are never learned from: said, not silent."""
    over = ["env.num_envs=4", "train.collect_steps=128", "train.total_steps=300", "eval.interval=0"]
    rows: list[dict] = []
    relayrl.train(relayrl.load_config("ppo", over), tmp_path / "r", progress=False, callbacks=[rows.append])
    assert ("train.total_steps=300 is not a whole number of rollouts of 128 env steps: the last 44 env steps are "
            "collected but not learned from (SB3's learn() would run one more whole rollout, to 384); "
            "train.total_steps=256 or 384 avoids it") in capsys.readouterr().err
    assert rows[-1]["step"] == 300 and rows[-1]["train_step"] == 2 * 10 * 2  # 2 rollouts x 10 epochs x 2 minibatches
    relayrl.train(relayrl.load_config("ppo", over[:2] + ["train.total_steps=256", "eval.interval=0"]), tmp_path / "s",
                  progress=False)
    assert "whole number of rollouts" not in capsys.readouterr().err
    from relayrl.training.notes import partial_rollout_note

    assert partial_rollout_note(relayrl.load_config("ppo")) is None  # 1,696 of 100,000 steps: unsaid
    assert partial_rollout_note(relayrl.load_config("ppo-cartpole", ["train.total_steps=1200"])) is not None  # 176
    # 256 env steps on 3 copies end at 258, one whole rollout of 258: nothing is left unlearned
    one = ["train.total_steps=256", "train.collect_steps=256", "env.num_envs=3"]
    assert partial_rollout_note(relayrl.load_config("ppo", one)) is None


def test_an_undefined_explained_variance_is_not_taken_for_divergence():
    """A rollout of equal returns (gamma 0 on CartPole) makes Var[R] = 0: the explained variance
    is NaN there, as in SB3, and the run goes on; a NaN loss still stops it."""
    from relayrl.agents.ppo.losses import explained_variance
    from relayrl.training.finite import non_finite_metrics

    ev = explained_variance(torch.tensor([0.5, 0.2, 0.9]), torch.ones(3))
    assert math.isnan(float(ev))
    metrics = {"loss": torch.tensor(0.3), "explained_variance": ev}
    assert non_finite_metrics(metrics, PPOAgent.undefined_metrics) is None
    assert non_finite_metrics(metrics) == "the explained variance was NaN"
    assert non_finite_metrics({**metrics, "loss": ev}, PPOAgent.undefined_metrics) == "the loss was NaN"


def test_a_run_whose_explained_variance_is_undefined_goes_on(tmp_path, monkeypatch):
    import relayrl.agents.ppo.agent as ppo_agent

    monkeypatch.setattr(ppo_agent, "explained_variance", lambda values, returns: torch.tensor(float("nan")))
    result = relayrl.train(relayrl.load_config("ppo-cartpole", [*BANDIT, "train.total_steps=512"]), tmp_path,
                           progress=False)
    assert result.final["step"] == 512


BANDIT = ["env.id=toy_envs:BetterAction", "env.num_envs=4", "train.total_steps=2048", "train.collect_steps=128",
          "agent.batch_size=32", "agent.n_epochs=4", "eval.interval=1024", "eval.episodes=20",
          "train.checkpoint_interval=0"]
REACH = ["env.id=toy_envs:Reach", "env.num_envs=4", "train.total_steps=12288", "train.collect_steps=256",
         "agent.batch_size=64", "agent.n_epochs=10", "agent.lr=3e-3", "agent.log_std_init=-0.5",
         "eval.interval=4096", "eval.episodes=20", "train.checkpoint_interval=0"]


def final(tmp_path, overrides, name="r", seed=0):
    cfg = relayrl.load_config("ppo-cartpole", overrides, seed=seed)
    relayrl.train(cfg, tmp_path / name, progress=False)
    return RunDir(tmp_path / name).read_metrics()


def test_ppo_learns_a_discrete_one_step_task(tmp_path):
    rows = final(tmp_path, BANDIT)
    assert rows[0]["average_return"] < 0.9 and rows[-1]["average_return"] == 1.0, rows


def test_ppo_learns_a_continuous_one_step_task(tmp_path):
    rows = final(tmp_path, REACH)
    assert rows[-1]["average_return"] > -0.3 > rows[0]["average_return"], rows


def test_sync_and_async_vectorization_give_the_same_run(tmp_path):
    over = [*BANDIT, "train.total_steps=512"]
    a = final(tmp_path, over, "sync")
    b = final(tmp_path, [*over, "env.vectorization=async", "env.num_workers=1"], "async")
    def rows(run):  # repr: NaN (no training episode yet at step 0) compares equal to itself
        return [repr({k: v for k, v in r.items() if k not in ("wall_time_s", "eval_s")}) for r in run]

    assert rows(a) == rows(b) and "losses/approx_kl" in a[-1]
    assert load_policy_file(tmp_path / "sync" / "policy" / "policy.pt")["state_dict"]["layers.0.weight"].equal(
        load_policy_file(tmp_path / "async" / "policy" / "policy.pt")["state_dict"]["layers.0.weight"])


def test_continuous_shared_async_run_resumes_bit_exact(tmp_path):
    """The conformance test resumes the discrete preset; this, a Gaussian policy on a shared
    network with its envs in a worker process."""
    over = [*REACH, "train.total_steps=1536", "eval.interval=512", "train.checkpoint_interval=512",
            "agent.shared=true", "agent.n_epochs=2", "env.vectorization=async", "env.num_workers=1"]
    cfg = relayrl.load_config("ppo-cartpole", over, seed=3)
    relayrl.train(cfg, tmp_path / "full", progress=False)
    cut_back(tmp_path / "full", tmp_path / "resumed")
    relayrl.train(cfg, tmp_path / "resumed", resume=True, progress=False)
    assert comparable(tmp_path / "resumed") == comparable(tmp_path / "full")
    assert_same_state(tmp_path / "full", tmp_path / "resumed")
    policy = relayrl.load_policy(tmp_path / "full", deterministic=False, seed=0)
    a = policy(torch.zeros(100, 2))
    assert a.shape == (100, 2) and a.std(0).min() > 0.1  # sampled around the mean


def test_squashed_and_clipped_actions_stay_inside_float32_bounds():
    """loc + scale * tanh(u) at tanh = -1 is 0.099999994 for Box(0.1, 0.3) in float32: to_bounds
    clips the squashed action too, so an env checking action_space.contains takes it."""
    from relayrl.agents.ppo.distributions import to_bounds

    low, high = torch.tensor([0.1]), torch.tensor([0.3])
    u = torch.tensor([[-50.0], [50.0], [0.0]])
    for tanh in (True, False):
        a = to_bounds(u, low, high, tanh)
        assert a.dtype == torch.float32 and bool(((a >= low) & (a <= high)).all()), (tanh, a)
    assert to_bounds(u, low, high, True)[:2, 0].tolist() == [low.item(), high.item()]


def test_a_rollout_of_one_step_per_env_copy_is_said():
    """env.num_envs raised to train.collect_steps (a cluster node's 256 copies): PPO learnt
    nothing without a word (SB3's n_steps is per copy, relayrl's collect_steps all copies')."""
    from relayrl.training.notes import short_rollout_note

    said = short_rollout_note(relayrl.load_config("ppo", ["env.num_envs=256", "train.collect_steps=256"]))
    assert said is not None and said.startswith("train.collect_steps=256 with env.num_envs=256: each rollout is one "
                                                "step of each env copy")
    assert short_rollout_note(relayrl.load_config("ppo", ["env.num_envs=8", "train.collect_steps=1024"])) is None
    assert short_rollout_note(relayrl.load_config("ppo-cartpole")) is None


def test_a_resume_past_a_lower_total_says_nothing_of_a_warm_up(tmp_path):
    from relayrl.training.notes import start_notes

    config = relayrl.load_config("dqn-cartpole", ["train.total_steps=1000", "train.initial_collect_steps=1000"])
    assert any("takes random actions only" in n for n in start_notes(config, tmp_path / "config.toml", False))
    assert not any("takes random actions only" in n for n in start_notes(config, tmp_path / "config.toml", True))


def test_gae_from_the_package_is_the_function_whatever_was_imported_first():
    """Its module was named gae too: once the agent had imported it, the package's `gae` was the module."""
    import relayrl.agents.ppo.agent  # noqa: F401  (imports the function's module)
    from relayrl.agents.ppo import gae as from_package
    from relayrl.agents.ppo.advantages import gae as own

    assert from_package is own
