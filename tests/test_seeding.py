"""Every random stream of a run derives from one SeedSequence(seed): no two coincide."""

import numpy as np
import pytest
import torch

import relayrl
from relayrl.envs.gym import GymBatchEnv
from relayrl.policies import TanhGaussianPolicy
from relayrl.seeding import EVAL_STRIDE, STREAMS, RunSeeds
from relayrl.training.local import LocalDriver
from relayrl.training.run_dir import RunDir


def _first_draws(gen: np.random.Generator) -> tuple[int, ...]:
    return tuple(gen.integers(0, 2**63, 4).tolist())


@pytest.mark.parametrize("seed", [0, 1, 2, 9_999, 10_000, 2**63 - 1])
def test_no_two_streams_of_a_run_share_numbers(seed):
    s = RunSeeds(seed)
    num_envs, evals, resumes = 64, 5, 5
    streams = {f"env {i}": np.random.default_rng(s.base("envs") + i) for i in range(num_envs)}
    streams |= {f"eval {k} copy {i}": np.random.default_rng(s.base("evaluation") + EVAL_STRIDE * k + i)
                for k in range(evals) for i in range(10)}
    # resumed at multiples of the evaluation stride: the resets that used to equal an evaluation's
    streams |= {f"resume at {k}": np.random.default_rng(s.base("resume") + EVAL_STRIDE * k) for k in range(resumes)}
    streams |= {name: s.generator(name) for name in ("exploration", "replay", "warmup")}
    for k in range(3):
        a = s.actor(k)
        streams |= {f"actor {k} env {i}": np.random.default_rng(a.base("envs") + i) for i in range(8)}
        streams |= {f"actor {k} {name}": a.generator(name) for name in ("exploration", "warmup")}
    draws = {name: _first_draws(g) for name, g in streams.items()}
    assert len(set(draws.values())) == len(draws)
    assert len({s.base(name) for name in STREAMS}) == len(STREAMS)


def test_seeds_out_of_range_are_refused():
    for bad in (-1, 2**63):
        with pytest.raises(ValueError, match="must be an integer in"):
            RunSeeds(bad)
        with pytest.raises(relayrl.errors.ConfigError, match="seed="):
            relayrl.load_config("dqn-cartpole-fast", seed=bad)


def _sequences_used(monkeypatch, tmp_path, overrides):
    """Every (entropy, spawn key) a run's construction seeded a NumPy generator or an env copy with."""
    used = []
    real_rng = np.random.default_rng

    def default_rng(seed=None):
        if isinstance(seed, np.random.SeedSequence):
            used.append(("rng", seed.entropy, tuple(seed.spawn_key)))
        elif seed is not None and not isinstance(seed, np.random.BitGenerator | np.random.Generator):
            used.append(("rng", int(seed), ()))
        return real_rng(seed)

    real_reset = GymBatchEnv.reset

    def reset(self, seed=None):
        if seed is not None:
            used.extend(("env", seed + i, ()) for i in range(self.num_envs))
        return real_reset(self, seed)

    monkeypatch.setattr(np.random, "default_rng", default_rng)
    monkeypatch.setattr(GymBatchEnv, "reset", reset)
    config = relayrl.load_config("dqn-cartpole-fast", overrides, seed=0)
    run = LocalDriver(config, RunDir(tmp_path / "r"), progress=False)
    run.close()
    return used


def test_a_runs_envs_exploration_replay_and_warmup_streams_are_distinct(monkeypatch, tmp_path):
    used = _sequences_used(monkeypatch, tmp_path, ["env.num_envs=4", "eval.episodes=4"])
    kinds = {kind for kind, _, _ in used}
    assert kinds == {"rng", "env"}
    # as SeedSequences: an int n is SeedSequence(n) with no spawn key
    seqs = [(entropy, key) for _, entropy, key in used]
    assert len(seqs) == len(set(seqs)), sorted(seqs)


def test_the_collect_policys_device_noise_generator_resumes_where_it_was():
    actor = torch.nn.Linear(3, 4)
    low, high = -np.ones(2, np.float32), np.ones(2, np.float32)

    def policy():
        return TanhGaussianPolicy(actor, low, high, torch.device("cpu"), False, np.random.default_rng(0))

    a = policy()
    obs = torch.randn(5, 3)
    for _ in range(3):
        a.act_on_device(obs)  # the generator exists and has moved on
    b = policy()
    b.load_state_dict(a.state_dict())
    assert torch.equal(a.act_on_device(obs), b.act_on_device(obs))
    c = policy()  # without the state: a fresh generator, other noise
    assert not torch.equal(a.act_on_device(obs), c.act_on_device(obs))


def test_a_generator_state_from_another_kind_of_device_seeds_it_instead():
    """A checkpoint written on a GPU (a CUDA generator's state is 16 bytes, a CPU's 5,056)
    resumes on a CPU: the generator is seeded from the state, the same way each time."""
    import struct

    import torch

    from relayrl.seeding import restore_generator

    gen = torch.Generator().manual_seed(3)
    saved = gen.get_state()
    expected = torch.rand(3, generator=gen)
    assert restore_generator(gen, saved) and torch.equal(torch.rand(3, generator=gen), expected)
    cuda_state = torch.tensor(list(struct.pack("<QQ", 12345, 0)), dtype=torch.uint8)
    assert not restore_generator(gen, cuda_state)
    first = torch.rand(3, generator=gen)
    restore_generator(gen, cuda_state)
    assert torch.equal(torch.rand(3, generator=gen), first)
