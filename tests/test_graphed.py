"""Gradient steps replayed from CUDA graphs (nn/graphed.py) against the same steps launched kernel
by kernel (RELAYRL_CUDA_GRAPHS=0): DQN and SAC, with and without importance weights, through a
learning-rate change; PPO through a learning-rate and clip-range schedule, with an epoch's
shorter last minibatch. The CUDA tests run where torch sees a GPU; the rest run everywhere."""

import numpy as np
import pytest
import torch

from relayrl.agents.dqn import DQNAgent, DQNConfig
from relayrl.agents.dqn.update import GraphedDQNUpdate
from relayrl.agents.ppo import PPOAgent, PPOConfig
from relayrl.agents.ppo.update import GraphedPPOUpdate
from relayrl.agents.sac import SACAgent, SACConfig
from relayrl.agents.sac.update import GraphedSACUpdate
from relayrl.nn.graphed import WARMUP, GraphedStep, cuda_graphs_enabled
from relayrl.optim import FastAdam
from relayrl.specs import ArraySpec, DiscreteSpec
from relayrl.types import Batch

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
STEPS = WARMUP + 5  # eager warm-up, the captured call, replays


def test_graphs_only_on_cuda_and_can_be_turned_off(monkeypatch):
    monkeypatch.delenv("RELAYRL_CUDA_GRAPHS", raising=False)
    assert not cuda_graphs_enabled(torch.device("cpu"))
    assert cuda_graphs_enabled(torch.device("cuda"))
    monkeypatch.setenv("RELAYRL_CUDA_GRAPHS", "0")
    assert not cuda_graphs_enabled(torch.device("cuda"))


def test_fast_adam_learning_rate_round_trips():
    opt = FastAdam([torch.zeros(2, requires_grad=True)], lr=1e-3)
    opt.lr = 5e-4
    state = opt.state_dict()
    other = FastAdam([torch.zeros(2, requires_grad=True)], lr=1e-3)
    other.load_state_dict(state)
    assert other.lr == pytest.approx(5e-4) and isinstance(other.lr, float)


@cuda
def test_graphed_step_runs_every_call_once():
    total = torch.zeros(3, device="cuda")

    def step(x: torch.Tensor) -> dict[str, torch.Tensor]:
        total.add_(x)
        return {"sum": total.sum()}

    graphed = GraphedStep(step)
    for i in range(STEPS):
        out = graphed(torch.full((3,), float(i), device="cuda"))
    assert float(out["sum"]) == pytest.approx(3 * sum(range(STEPS)))


def dqn_pair(monkeypatch, **kw):
    cfg = DQNConfig(hidden=[32, 32], batch_size=16, lr=1e-3, target_update_period=10**6, double=True, **kw)
    agents = []
    for graphs in ("1", "0"):
        monkeypatch.setenv("RELAYRL_CUDA_GRAPHS", graphs)
        torch.manual_seed(0)
        agents.append(DQNAgent(ArraySpec((4,), torch.float32), DiscreteSpec(3), cfg, torch.device("cuda"),
                               np.random.default_rng(0)))
    assert isinstance(agents[0].update, GraphedDQNUpdate) and not isinstance(agents[1].update, GraphedDQNUpdate)
    return agents


def dqn_batch(seed: int, weighted: bool) -> Batch:
    g = torch.Generator().manual_seed(seed)
    n = 16
    weight = torch.rand(n, generator=g) + 0.5 if weighted else None
    b = Batch(torch.randn(n, 4, generator=g), torch.randint(3, (n,), generator=g), torch.randn(n, generator=g),
              torch.randn(n, 4, generator=g), torch.full((n,), 0.99), weight)
    return Batch(*(None if x is None else x.cuda() for x in b))


@cuda
@pytest.mark.parametrize("weighted", [False, True])
def test_graphed_dqn_matches_eager(monkeypatch, weighted):
    graphed, eager = dqn_pair(monkeypatch)
    for i in range(STEPS):
        if i == STEPS - 2:  # a schedule's change reaches the replays
            graphed.optimizer.lr = eager.optimizer.lr = 0.0
        a, b = graphed.train(dqn_batch(i, weighted)), eager.train(dqn_batch(i, weighted))
        torch.testing.assert_close(a["td_error"], b["td_error"], atol=1e-5, rtol=1e-4)
    for p, q in zip(graphed.online.parameters(), eager.online.parameters(), strict=True):
        torch.testing.assert_close(p, q, atol=1e-5, rtol=1e-4)


@cuda
def test_graphed_dqn_captures_each_batch_signature(monkeypatch):
    graphed, eager = dqn_pair(monkeypatch)
    for i in range(STEPS):  # weighted and unweighted batches take turns: two graphs
        for weighted in (False, True):
            graphed.train(dqn_batch(i, weighted))
            eager.train(dqn_batch(i, weighted))
    for p, q in zip(graphed.online.parameters(), eager.online.parameters(), strict=True):
        torch.testing.assert_close(p, q, atol=1e-5, rtol=1e-4)


def sac_pair(monkeypatch):
    obs = ArraySpec((3,), torch.float32, -np.ones(3), np.ones(3))
    act = ArraySpec((2,), torch.float32, np.array([-2.0, 0.0]), np.array([2.0, 1.0]))
    cfg = SACConfig(actor_hidden=[32, 32], critic_hidden=[32, 32], batch_size=16)
    agents = []
    for graphs in ("1", "0"):
        monkeypatch.setenv("RELAYRL_CUDA_GRAPHS", graphs)
        torch.manual_seed(0)
        agents.append(SACAgent(obs, act, cfg, torch.device("cuda"), np.random.default_rng(0)))
    assert isinstance(agents[0].update, GraphedSACUpdate) and not isinstance(agents[1].update, GraphedSACUpdate)
    return agents


def sac_batch(seed: int) -> Batch:
    g = torch.Generator().manual_seed(seed)
    n = 16
    action = torch.stack([torch.rand(n, generator=g) * 4 - 2, torch.rand(n, generator=g)], dim=1)
    b = Batch(torch.randn(n, 3, generator=g), action, torch.randn(n, generator=g), torch.randn(n, 3, generator=g),
              torch.full((n,), 0.99), None)
    return Batch(*(None if x is None else x.cuda() for x in b))


@cuda
def test_graphed_sac_draws_fresh_noise_each_replay(monkeypatch):
    graphed, _ = sac_pair(monkeypatch)
    for opt in (graphed.actor_opt, graphed.critic_opt, graphed.alpha_opt):
        opt.lr = 0.0  # the weights stay put: only the noise can move the entropy
    entropies = [float(graphed.train(sac_batch(0))["entropy"]) for _ in range(STEPS)]
    assert len(set(entropies[WARMUP:])) == len(entropies[WARMUP:])


@cuda
def test_graphed_dqn_follows_a_checkpoint_loaded_after_capture(monkeypatch):
    graphed, eager = dqn_pair(monkeypatch)
    for i in range(STEPS):  # captured by now
        graphed.train(dqn_batch(i, False))
        eager.train(dqn_batch(i, False))
    saved = graphed.state_dict()
    saved = {**saved, "online": {k: v.clone() for k, v in saved["online"].items()}}
    for i in range(3):  # moves away from the checkpoint
        graphed.train(dqn_batch(100 + i, False))
    graphed.load_state_dict(saved)  # in place: the graph's tensors take the checkpoint
    for i in range(3):
        a, b = graphed.train(dqn_batch(200 + i, False)), eager.train(dqn_batch(200 + i, False))
        torch.testing.assert_close(a["td_error"], b["td_error"], atol=1e-5, rtol=1e-4)


@cuda
def test_graphed_sac_matches_eager(monkeypatch):
    graphed, eager = sac_pair(monkeypatch)
    for i in range(STEPS):
        a, b = graphed.train(sac_batch(i)), eager.train(sac_batch(i))
        torch.testing.assert_close(a["critic_loss"], b["critic_loss"], atol=1e-4, rtol=1e-4)
    for p, q in zip([*graphed.actor.parameters(), graphed.log_alpha], [*eager.actor.parameters(), eager.log_alpha],
                    strict=True):
        torch.testing.assert_close(p, q, atol=1e-4, rtol=1e-4)


@cuda
def test_greedy_policy_replays_see_weights_updated_in_place(monkeypatch):
    from relayrl.nn import MLP
    from relayrl.policies import GreedyPolicy

    net = MLP(4, [16], 3, "relu").cuda()
    graphed = GreedyPolicy(net, torch.device("cuda"))
    monkeypatch.setenv("RELAYRL_CUDA_GRAPHS", "0")
    eager = GreedyPolicy(net, torch.device("cuda"))
    g = torch.Generator().manual_seed(0)
    for i in range(2 * STEPS):
        if i == STEPS:
            with torch.no_grad():
                for p in net.parameters():
                    p.mul_(-1.5)
        obs = torch.randn(5, 4, generator=g)
        assert torch.equal(graphed(obs), eager(obs))


FRAMES = ArraySpec((4, 84, 84), torch.uint8, np.zeros((4, 84, 84)), np.full((4, 84, 84), 255.0))


def block_frames(g: torch.Generator, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """uint8 [n, 4, 84, 84] stacks with a bright block in one of three bands, and the band."""
    band = torch.randint(3, (n,), generator=g)
    x = torch.zeros(n, *FRAMES.shape, dtype=torch.uint8)
    for j in range(3):
        x[band == j, :, 28 * j:28 * j + 28, 30:54] = 255
    return x, band


@cuda
def test_graphed_pixel_dqn_matches_eager_as_the_learner_drives_it(monkeypatch):
    """Pong's net and frames, fed as the Learner feeds them: chunks of two batches with the
    target network's Q-values prepared ahead, and a lone unprepared batch where a chunk is cut at
    a target copy (every third step: two graphs sharing the parameters and Adam's state, each
    warmed up, captured and replayed within the 18 steps)."""
    monkeypatch.setattr(torch.backends.cudnn, "deterministic", True)  # the same kernels each way
    monkeypatch.setattr(torch.backends.cudnn, "benchmark", False)
    cfg = DQNConfig(network="nature_cnn", batch_size=32, lr=2.5e-4, target_update_period=3, double=True,
                    grad_clip=10.0)
    agents, losses = [], []
    for graphs in ("1", "0"):
        monkeypatch.setenv("RELAYRL_CUDA_GRAPHS", graphs)
        torch.manual_seed(0)
        agents.append(DQNAgent(FRAMES, DiscreteSpec(6), cfg, torch.device("cuda"), np.random.default_rng(0)))
    for agent in agents:
        g, n, seen = torch.Generator().manual_seed(1), 32, []
        while len(seen) < 18:
            k = min(2, agent.prepare_horizon())
            obs, band = block_frames(g, k * n)
            action = torch.randint(6, (k * n,), generator=g)
            reward = (action % 3 == band).float() * 2 - 1  # which band the block is in
            nxt, _ = block_frames(g, k * n)
            chunk = agent.prepare(Batch(*(x.cuda() for x in (obs, action, reward, nxt)),
                                        torch.full((k * n,), 0.97, device="cuda"), None), k)
            for j in range(k):
                metrics = agent.train(type(chunk)(*(x[j * n:(j + 1) * n] if isinstance(x, torch.Tensor) else x
                                                    for x in chunk)))
                seen.append(float(metrics["loss"]))
        losses.append(seen)
    torch.testing.assert_close(torch.tensor(losses[0]), torch.tensor(losses[1]), atol=1e-4, rtol=1e-3)
    graphed, eager = agents
    # Adam's normalised steps magnify rounding where a gradient is ~0: a bound of a few steps' size
    for p, q in zip(graphed.online.parameters(), eager.online.parameters(), strict=True):
        torch.testing.assert_close(p, q, atol=2e-3, rtol=1e-2)


@cuda
def test_greedy_policy_on_pixels_replays_as_eager_on_pinned_frames_in_inference_mode(monkeypatch):
    """As a run's evaluations call it: pinned uint8 stacks (ale-py's frames on a CUDA run),
    inference_mode, the network trained in place between calls."""
    from relayrl.policies import GreedyPolicy

    agent = DQNAgent(FRAMES, DiscreteSpec(6), DQNConfig(network="nature_cnn", batch_size=8), torch.device("cuda"),
                     np.random.default_rng(0))
    graphed = GreedyPolicy(agent.online, torch.device("cuda"))
    monkeypatch.setenv("RELAYRL_CUDA_GRAPHS", "0")
    eager = GreedyPolicy(agent.online, torch.device("cuda"))
    g = torch.Generator().manual_seed(0)
    for i in range(2 * STEPS):
        obs = block_frames(g, 5)[0].pin_memory()
        with torch.inference_mode():
            a, b = graphed(obs), eager(obs)
        assert torch.equal(a, b), i
        if i == STEPS:
            with torch.no_grad():
                for p in agent.online.parameters():
                    p.add_(torch.randn(p.shape, generator=g).cuda() * 0.05)


@cuda
@pytest.mark.parametrize("discrete", [False, True])
def test_ppo_device_policy_graphed_draws_as_eager(monkeypatch, discrete):
    """The forward pass and the draw in one graph, its generator registered: the same actions
    as launched op by op from the same seed, through a weight change."""
    from relayrl.agents.ppo.device_policy import PPODevicePolicy
    from relayrl.nn import MLP

    net = MLP(3, [16], 2, "tanh").cuda()
    log_std = None if discrete else torch.full((2,), -0.5, device="cuda")
    policies = []
    for graphs in ("1", "0"):
        monkeypatch.setenv("RELAYRL_CUDA_GRAPHS", graphs)
        policies.append(PPODevicePolicy(net, log_std, None, torch.device("cuda"), seed=7))
    graphed, eager = policies
    kept = []
    for i in range(2 * STEPS):
        if i == STEPS:
            with torch.no_grad():
                for p in net.parameters():
                    p.mul_(-1.5)
        if i == STEPS + 2:  # a checkpoint's generator state loaded after capture
            graphed.load_state_dict(eager.state_dict())
        obs = torch.randn(6, 3, device="cuda")
        a, b = graphed(obs), eager(obs)
        kept.append((a, b))
        assert torch.equal(a, b), i
    assert all(torch.equal(a, b) for a, b in kept)  # each call's action is its own tensor


@cuda
def test_signatures_beyond_max_graphs_run_eagerly():
    total = torch.zeros((), device="cuda")

    def step(x: torch.Tensor) -> dict[str, torch.Tensor]:
        total.add_(x.sum())
        return {"total": total}

    graphed = GraphedStep(step, max_graphs=1)
    expected = 0.0
    for i in range(STEPS):
        for n in (1, 2):  # the second shape never gets a graph
            graphed(torch.full((n,), float(i), device="cuda"))
            expected += n * i
    assert float(total) == pytest.approx(expected)


def ppo_agent(device: str, **kw) -> PPOAgent:
    obs = ArraySpec((3,), torch.float32, -np.ones(3), np.ones(3))
    act = ArraySpec((2,), torch.float32, -np.ones(2), np.ones(2))
    cfg = PPOConfig(hidden=[16, 16], batch_size=16, n_epochs=2, clip_range_end=0.0)
    torch.manual_seed(0)
    return PPOAgent(obs, act, cfg, torch.device(device), np.random.default_rng(0), total_steps=100, **kw)


def ppo_rollout(seed: int, device: str) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    t, b = 6, 4  # 24 steps: minibatches of 16 and 8
    r = {"obs": torch.randn(1, t, b, 3, generator=g), "action": torch.randn(1, t, b, 2, generator=g),
         "reward": torch.randn(1, t, b, generator=g), "next_obs": torch.randn(1, t, b, 3, generator=g),
         "terminated": torch.rand(1, t, b, generator=g) < 0.1, "truncated": torch.zeros(1, t, b, dtype=torch.bool)}
    return {k: v.to(device) for k, v in r.items()}


def test_ppo_reference_takes_the_clip_range_as_a_tensor():
    a, b = ppo_agent("cpu", hand_written=False), ppo_agent("cpu", hand_written=False)
    r = ppo_rollout(0, "cpu")
    mb = [x.reshape(24, *x.shape[3:])[:16] for x in (r["obs"], r["action"], r["reward"], r["reward"])]
    args = (*mb[:2], mb[2] * 0.1, mb[3], mb[2], mb[3] * 2)
    torch.testing.assert_close(a.update(*args, 0.1), b.update(*args, torch.tensor(0.1)))


@cuda
def test_graphed_ppo_matches_eager(monkeypatch):
    monkeypatch.setenv("RELAYRL_CUDA_GRAPHS", "1")
    graphed = ppo_agent("cuda")
    monkeypatch.setenv("RELAYRL_CUDA_GRAPHS", "0")
    eager = ppo_agent("cuda", hand_written=False)
    assert isinstance(graphed.update, GraphedPPOUpdate) and not isinstance(eager.update, GraphedPPOUpdate)
    for i in range(STEPS):  # one graph per rollout signature: warm-up, capture, replays
        if i == STEPS - 2:  # the schedule's end reaches the replays: clip range 0
            graphed.set_progress(100)
            eager.set_progress(100)
        a, b = graphed.train(ppo_rollout(i, "cuda")), eager.train(ppo_rollout(i, "cuda"))
        torch.testing.assert_close(a["loss"], b["loss"], atol=1e-5, rtol=1e-4)
    # At clip range 0 every ratio off 1 is clipped: all but the first minibatch's (3 of 4).
    assert float(a["clip_fraction"]) > 0.5
    for p, q in zip(graphed.net.parameters(), eager.net.parameters(), strict=True):
        torch.testing.assert_close(p, q, atol=1e-5, rtol=1e-4)


def test_one_process_container_keeps_references_where_the_weights_are():
    from relayrl.training.variables import VariableContainer

    w = [torch.ones(3)]
    assert VariableContainer(copy=False).pull()[1] is None
    shared, snap = VariableContainer(copy=False), VariableContainer(copy=True)
    shared.push(w)
    snap.push(w)
    w[0].add_(1)
    assert torch.equal(shared.pull()[1][0], w[0]) and shared.pull()[1][0].data_ptr() == w[0].data_ptr()
    assert torch.equal(snap.pull()[1][0], torch.ones(3))
