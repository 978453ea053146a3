"""Every algorithm's losses through torch.compile (`nn.graphed.compiled`, RELAYRL_COMPILE)
against the same losses run as written: the same training, step after step. `aot_eager` traces
them as inductor does (one graph each, `fullgraph=True`: no Python left in between) without
generating code; the inductor runs on a CPU are slow-marked (seconds of compiling each). On
CUDA (where torch sees a GPU) inductor's kernels run inside the updates' CUDA graphs, against
the same graphs of the losses as written."""

import numpy as np
import pytest
import torch

from relayrl.agents.dqn import DQNAgent, DQNConfig
from relayrl.agents.ppo import PPOAgent, PPOConfig
from relayrl.agents.sac import SACAgent, SACConfig
from relayrl.errors import UserError
from relayrl.nn.graphed import RECOMPILE_LIMIT, WARMUP, compiled, recompile_limit_name
from relayrl.specs import ArraySpec, DiscreteSpec
from relayrl.types import Batch

VEC = ArraySpec((3,), torch.float32)
IMAGE = ArraySpec((2, 36, 36), torch.uint8, np.zeros((2, 36, 36)), np.full((2, 36, 36), 255.0))
BOX = ArraySpec((2,), torch.float32, np.array([-2.0, 0.0]), np.array([2.0, 1.0]))
# (device, RELAYRL_COMPILE)
STEPS = WARMUP + 2  # per batch signature (weighted or not): warm-up calls, the captured one, a replay
BACKENDS = [("cpu", "aot_eager"), pytest.param(("cpu", "inductor"), marks=pytest.mark.slow),
            pytest.param(("cuda", "1"), marks=pytest.mark.skipif(not torch.cuda.is_available(),
                                                                 reason="needs a CUDA device"))]


def test_compiled_is_the_function_itself_unless_asked(monkeypatch):
    def losses(x: torch.Tensor) -> torch.Tensor:
        return x * 2

    monkeypatch.delenv("RELAYRL_COMPILE", raising=False)
    assert compiled(losses) is losses
    monkeypatch.setenv("RELAYRL_COMPILE", "0")
    assert compiled(losses) is losses
    monkeypatch.setenv("RELAYRL_COMPILE", "aot_eager")
    fn = compiled(losses)
    assert fn is not losses and torch.equal(fn(torch.ones(2)), torch.full((2,), 2.0))
    for bad in ("true", "cudagraphs"):
        monkeypatch.setenv("RELAYRL_COMPILE", bad)
        with pytest.raises(UserError, match=rf"RELAYRL_COMPILE='{bad}' is not valid; valid: 0 \(off\), 1 "
                                            r"\(inductor\), or a torch.compile backend other than cudagraphs: "
                                            r"aot_eager, .*inductor"):
            compiled(losses)


def test_cuda_graphs_take_0_or_1_and_any_other_value_is_one_line(monkeypatch):
    from relayrl.nn.graphed import cuda_graphs_enabled

    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    monkeypatch.delenv("RELAYRL_CUDA_GRAPHS", raising=False)
    assert cuda_graphs_enabled(cuda) and not cuda_graphs_enabled(cpu)
    monkeypatch.setenv("RELAYRL_CUDA_GRAPHS", "0")
    assert not cuda_graphs_enabled(cuda)
    monkeypatch.setenv("RELAYRL_CUDA_GRAPHS", "false")  # was read as on
    with pytest.raises(UserError, match=r"^RELAYRL_CUDA_GRAPHS='false' is not valid; valid: 1 \(capture CUDA graphs, "):
        cuda_graphs_enabled(cpu)


def test_compiling_leaves_room_for_the_variants_of_many_agents(monkeypatch):
    name = recompile_limit_name()
    with torch._dynamo.config.patch(**{name: 8}):  # torch's default, restored after
        monkeypatch.setenv("RELAYRL_COMPILE", "0")
        compiled(lambda x: x)
        assert getattr(torch._dynamo.config, name) == 8  # nothing compiled: torch's setting is left alone
        monkeypatch.setenv("RELAYRL_COMPILE", "aot_eager")
        compiled(lambda x: x)
        assert getattr(torch._dynamo.config, name) == RECOMPILE_LIMIT


def test_ppo_clip_range_goes_in_as_a_tensor_only_where_compiled(monkeypatch):
    for setting, as_tensor in (("0", False), ("aot_eager", True)):
        monkeypatch.setenv("RELAYRL_COMPILE", setting)
        agent = PPOAgent(VEC, BOX, PPOConfig(squash="tanh"), torch.device("cpu"), np.random.default_rng(0),
                         hand_written=False)
        assert agent.update.clip_as_tensor is as_tensor


def once_on_cuda(backend, first_case: bool) -> None:
    """One case per algorithm on CUDA: a cold compile there costs seconds each."""
    if backend[0] == "cuda" and not first_case:
        pytest.skip("on CUDA the first case of each algorithm stands for the rest")


def pair(monkeypatch, backend, make):
    """Two agents in the same state on the autograd reference: losses compiled, and as written."""
    device, setting = backend
    agents = []
    for compile_setting in (setting, "0"):
        monkeypatch.setenv("RELAYRL_COMPILE", compile_setting)
        torch.manual_seed(0)
        agents.append(make(torch.device(device)))
    return agents


def on(device, batch):
    return Batch(*(None if x is None else x.to(device) for x in batch))


def assert_same(a, b, what):
    for x, y in zip(a, b, strict=True):
        assert torch.allclose(x.cpu(), y.cpu(), rtol=1e-4, atol=1e-5), what


def image_batch(n, seed):
    g = torch.Generator().manual_seed(seed)
    frames = torch.randint(0, 256, (2, n, *IMAGE.shape), generator=g, dtype=torch.uint8)
    return frames[0], frames[1], g


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("obs", ["vector", "image"])
@pytest.mark.parametrize("options", [{"double": True}, {"double": False, "loss": "mse", "grad_clip": 0.0}])
def test_dqn(monkeypatch, backend, obs, options):
    once_on_cuda(backend, obs == "vector" and options["double"])
    spec = VEC if obs == "vector" else IMAGE
    cfg = DQNConfig(hidden=[16, 16], lr=1e-3, target_update_period=3, **options)
    made = pair(monkeypatch, backend, lambda device: DQNAgent(spec, DiscreteSpec(3), cfg, device,
                                                              np.random.default_rng(0), hand_written=False))
    for step in range(2 * STEPS):
        n = 8
        if obs == "vector":
            g = torch.Generator().manual_seed(step)
            o, o2 = torch.randn(n, 3, generator=g), torch.randn(n, 3, generator=g)
        else:
            o, o2, g = image_batch(n, step)
        weight = torch.rand(n, generator=g) + 0.5 if step % 2 else None
        b = on(backend[0], Batch(o, torch.randint(3, (n,), generator=g), torch.randn(n, generator=g), o2,
                                 torch.full((n,), 0.99), weight))
        metrics = [agent.train(b) for agent in made]
        assert_same([metrics[0]["td_error"]], [metrics[1]["td_error"]], f"td_error at step {step}")
    assert_same(list(made[0].online.parameters()), list(made[1].online.parameters()), "parameters")


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("options", [{}, {"autotune_alpha": False, "grad_clip": 0.5}])
def test_sac(monkeypatch, backend, options):
    once_on_cuda(backend, not options)
    cfg = SACConfig(actor_hidden=[16, 16], critic_hidden=[16, 16], batch_size=8, **options)
    made = pair(monkeypatch, backend, lambda device: SACAgent(VEC, BOX, cfg, device, np.random.default_rng(0),
                                                              hand_written=False))
    for step in range(2 * STEPS):
        g = torch.Generator().manual_seed(step)
        n = 8
        action = torch.stack([torch.rand(n, generator=g) * 4 - 2, torch.rand(n, generator=g)], dim=1)
        weight = torch.rand(n, generator=g) + 0.5 if step % 2 else None
        b = on(backend[0], Batch(torch.randn(n, 3, generator=g), action, torch.randn(n, generator=g),
                                 torch.randn(n, 3, generator=g), torch.full((n,), 0.99), weight))
        metrics = [agent.train(b) for agent in made]
        for key in metrics[1]:
            assert_same([metrics[0][key].detach()], [metrics[1][key].detach()], f"{key} at step {step}")
    for a, b_ in ((made[0].actor, made[1].actor), (made[0].critic, made[1].critic)):
        assert_same(list(a.parameters()), list(b_.parameters()), "parameters")
    assert_same([made[0].log_alpha], [made[1].log_alpha], "log alpha")


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("action", ["discrete", "box", "box-tanh", "box-shared-vf-clip"])
def test_ppo(monkeypatch, backend, action):
    once_on_cuda(backend, action == "box")
    options = {"box-tanh": {"squash": "tanh"}, "box-shared-vf-clip": {"shared": True, "clip_range_vf": 0.2}}
    cfg = PPOConfig(hidden=[16, 16], batch_size=8, n_epochs=2, max_grad_norm=0.5, **options.get(action, {}))
    spec = DiscreteSpec(3) if action == "discrete" else BOX
    made = pair(monkeypatch, backend, lambda device: PPOAgent(VEC, spec, cfg, device, np.random.default_rng(0),
                                                              total_steps=100, hand_written=False))
    for step in range(STEPS):
        g = torch.Generator().manual_seed(step)
        t, b = 5, 4
        acts = torch.randint(0, 3, (1, t, b), generator=g) if action == "discrete" else torch.randn(1, t, b, 2,
                                                                                                   generator=g)
        done = torch.rand(1, t, b, generator=g)
        rollout = {"obs": torch.randn(1, t, b, 3, generator=g), "action": acts,
                   "reward": torch.randn(1, t, b, generator=g), "next_obs": torch.randn(1, t, b, 3, generator=g),
                   "terminated": done < 0.1, "truncated": done > 0.9}
        metrics = [agent.train(rollout) for agent in made]
        for key in ("policy_loss", "value_loss", "approx_kl", "loss"):
            assert_same([metrics[0][key]], [metrics[1][key]], f"{key} at step {step}")
    assert_same(list(made[0].net.parameters()), list(made[1].net.parameters()), "parameters")


def test_ppo_clip_schedule_compiles_once(monkeypatch):
    """A clip range a schedule moves goes into the compiled losses as a tensor: a Python float
    would compile a graph per value and soon hit torch's recompile limit (an error with
    fullgraph)."""
    cfg = PPOConfig(hidden=[8], batch_size=10, n_epochs=1, clip_range_end=0.0)
    made = pair(monkeypatch, ("cpu", "aot_eager"), lambda device: PPOAgent(
        VEC, BOX, cfg, device, np.random.default_rng(0), total_steps=120, hand_written=False))
    for step in range(12):  # twelve clip ranges, more than the recompile limit of 8
        g = torch.Generator().manual_seed(step)
        rollout = {"obs": torch.randn(1, 5, 2, 3, generator=g), "action": torch.randn(1, 5, 2, 2, generator=g),
                   "reward": torch.randn(1, 5, 2, generator=g), "next_obs": torch.randn(1, 5, 2, 3, generator=g),
                   "terminated": torch.zeros(1, 5, 2, dtype=torch.bool),
                   "truncated": torch.zeros(1, 5, 2, dtype=torch.bool)}
        for agent in made:
            agent.set_progress(step * 10)
        metrics = [agent.train(rollout) for agent in made]
        assert_same([metrics[0]["loss"]], [metrics[1]["loss"]], f"loss at step {step}")
    assert made[0].clip_range < 0.02

