"""What every algorithm in the registry promises, one test each, parametrised over the registry:
its saved policy loads and acts as the agent does, its exported policy.pt2 matches the torch
policy in a process without relayrl, a resumed run is the uninterrupted one bit for bit (or,
for an algorithm whose runs are not checkpointed, `--resume` is refused), and bad input on the
command line is one line and exit 2.

An algorithm added to the registry fails `test_every_algorithm_has_a_case` until it has a
small run in CASES: a few seconds of training on a tiny env.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from test_resume import DQN, SAC, assert_same_state, comparable, cut_back

import relayrl
from relayrl.agents.registry import ALGORITHMS, algorithm
from relayrl.envs import make_env
from relayrl.errors import UserError
from relayrl.export import load_policy_state
from relayrl.training.checkpoint import load_latest_checkpoint
from relayrl.training.run_dir import RunDir

# algo -> (preset, overrides): a short run that writes checkpoints (where the algorithm has them)
CASES = {
    "dqn": ("dqn-cartpole-fast", DQN),
    "sac": ("sac-pendulum", SAC),
    "ppo": ("ppo-cartpole", ["train.total_steps=1536", "eval.interval=512", "eval.episodes=3",
                             "train.checkpoint_interval=512", "agent.hidden=[16]", "agent.n_epochs=2",
                             "agent.batch_size=64"]),
    "bptt": ("bptt-pendulum", ["train.total_steps=9600", "eval.interval=3200"]),  # 3 iterations
}
NAMES = sorted(ALGORITHMS)


def test_every_algorithm_has_a_case():
    assert sorted(CASES) == NAMES


@pytest.mark.parametrize("name", NAMES)
def test_registry_entry_resolves(name):
    entry = algorithm(name)
    assert entry.config().validate() is None  # the defaults are valid
    module = entry.policy_module()
    assert callable(module.load) and callable(module.deterministic_module) and callable(module.action_space)
    if entry.agent is not None:
        assert isinstance(entry.agent(), type)
    if entry.trainer is not None:
        assert callable(entry.direct_trainer().train) and callable(entry.direct_trainer().final_scalars)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """algo -> (config, run directory of a finished run), each trained once for the module."""
    made: dict = {}

    def get(name):
        if name not in made:
            preset, over = CASES[name]
            cfg = relayrl.load_config(preset, over, seed=3)
            root = tmp_path_factory.mktemp(name) / "full"
            relayrl.train(cfg, root, progress=False)
            made[name] = (cfg, root)
        return made[name]

    return get


def observations(state, n=7):
    torch.manual_seed(0)
    if "obs_shape" in state:
        return torch.randint(0, 256, (n, *state["obs_shape"]), dtype=torch.uint8)
    return torch.randn(n, state["obs_dim"]) * 2


@pytest.mark.parametrize("name", NAMES)
def test_saved_policy_round_trip(runs, name):
    cfg, root = runs(name)
    entry = algorithm(name)
    state = load_policy_state(root)
    assert state["kind"] == entry.policy_kind and state["env_steps"] == cfg.train.total_steps
    policy = relayrl.load_policy(root)
    obs = observations(state)
    actions = policy(obs)
    assert actions.shape[0] == obs.shape[0] and torch.equal(policy(obs), actions)
    if not entry.agent:
        return
    # The checkpointed agent, rebuilt by the registry, acts as the saved policy does.
    env = make_env(cfg.env.id)
    agent = entry.make_agent(cfg.agent, env.observation_spec, env.action_spec, torch.device("cpu"),
                            np.random.default_rng(0), cfg.train.total_steps)
    env.close()
    agent.load_state_dict(load_latest_checkpoint(root / "checkpoints")["agent"])
    assert torch.equal(agent.eval_policy()(obs), actions)


@pytest.mark.parametrize("name", NAMES)
def test_exported_policy_matches_the_torch_policy_without_relayrl(runs, name, tmp_path):
    _, root = runs(name)
    state = load_policy_state(root)
    obs = observations(state)
    expected = relayrl.load_policy(root)(obs)
    path = relayrl.export_policy(root, tmp_path / "policy.pt2")
    assert path.name == "policy.pt2"
    np.save(tmp_path / "obs.npy", obs.numpy())
    code = (f"import sys, numpy, torch; m = torch.export.load({str(path)!r}).module(); "
            f"a = m(torch.from_numpy(numpy.load({str(tmp_path / 'obs.npy')!r}))); "
            "assert 'relayrl' not in sys.modules; numpy.save(sys.argv[1], a.detach().numpy())")
    subprocess.run([sys.executable, "-c", code, str(tmp_path / "out.npy")], check=True, cwd=tmp_path)
    assert np.allclose(np.load(tmp_path / "out.npy"), expected.numpy(), atol=1e-6)


@pytest.mark.parametrize("name", NAMES)
def test_resume_is_bit_exact_or_refused(runs, name, tmp_path):
    cfg, root = runs(name)
    if not algorithm(name).resumable:
        with pytest.raises(UserError, match="not checkpointed"):
            relayrl.train(cfg, root, resume=True, progress=False)
        return
    cut_back(root, tmp_path / "resumed")
    relayrl.train(cfg, tmp_path / "resumed", resume=True, progress=False)
    assert comparable(tmp_path / "resumed") == comparable(root)
    assert_same_state(root, tmp_path / "resumed")


@pytest.mark.parametrize("name", NAMES)
def test_cli_bad_input_is_one_line_and_exit_2(name, cli_env, tmp_path):
    preset, _ = CASES[name]
    r = subprocess.run([sys.executable, "-m", "relayrl", "train", preset, "--run-dir", str(tmp_path / "z"),
                        "--set", "agent.batch_size=0"], capture_output=True, text=True, env=cli_env, timeout=300)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("relayrl: error:") and "agent.batch_size" in lines[0], r.stderr
    assert not (tmp_path / "z").exists()


@pytest.mark.parametrize("name", NAMES)
def test_loaded_policy_takes_numpy_torch_single_and_batched(runs, name):
    _, root = runs(name)
    state = load_policy_state(root)
    obs = observations(state)  # torch [7, *obs_shape] of the policy's dtype
    policy = relayrl.load_policy(root)
    expected = policy.batched(obs)
    batch64 = obs.numpy().astype(np.float64)
    for given in (obs.numpy(), batch64):  # NumPy in, NumPy out, float64 cast
        actions = policy(given)
        assert isinstance(actions, np.ndarray) and np.array_equal(actions, expected.numpy())
    one = policy(batch64[0])  # one observation in, one action out
    assert isinstance(one, (np.ndarray, np.generic)) and np.shape(one) == tuple(expected.shape[1:])
    # (a batch of one may round differently from a batch of seven in the matmul)
    assert np.allclose(one, expected[0].numpy(), atol=1e-6)
    single = policy(obs.double()[0])  # torch in, torch out
    assert isinstance(single, torch.Tensor) and torch.allclose(single.double(), expected[0].double(), atol=1e-6)
    action, recurrent_state = policy.predict(obs.numpy()[0], deterministic=True)  # SB3's spelling
    assert recurrent_state is None and np.allclose(action, expected[0].numpy(), atol=1e-6)
    for wrong in (np.zeros((3, 99)), torch.zeros((3, 99), dtype=obs.dtype)):  # a tensor in its dtype too
        with pytest.raises(UserError, match="does not fit this policy"):
            policy(wrong)
    if name == "sac":
        sampled, _ = policy.predict(obs.numpy(), deterministic=False)
        assert sampled.shape == expected.shape and not np.array_equal(sampled, expected.numpy())


@pytest.mark.parametrize("name", NAMES)
def test_onnx_export_matches_the_torch_policy(runs, name, tmp_path):
    pytest.importorskip("onnx")
    ort = pytest.importorskip("onnxruntime")
    _, root = runs(name)
    state = load_policy_state(root)
    obs = observations(state)
    expected = relayrl.load_policy(root)(obs)
    path = relayrl.export_policy(root, tmp_path / "sub" / "policy.onnx", format="onnx")  # folders are created
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    (actions,) = session.run(None, {"obs": obs.numpy()})
    assert np.allclose(actions, expected.numpy(), atol=1e-5)
    sig = json.loads(path.with_name("policy.onnx.json").read_text())
    assert sig["input"] == {"name": "obs", "dtype": str(obs.dtype).removeprefix("torch."),
                            "shape": ["batch", *obs.shape[1:]]}
    assert sig["output"]["shape"] == ["batch", *expected.shape[1:]]


@pytest.mark.parametrize("name", NAMES)
def test_eval_interval_zero_evaluates_once_at_the_end(name, tmp_path):
    preset, over = CASES[name]
    cfg = relayrl.load_config(preset, [*over, "eval.interval=0"], seed=3)
    result = relayrl.train(cfg, tmp_path / "r", progress=False)
    rows = RunDir(tmp_path / "r").read_metrics()
    assert [r["step"] for r in rows] == [cfg.train.total_steps] and result.final == rows[0]
    assert relayrl.load_policy(tmp_path / "r") is not None


def test_eval_interval_must_not_be_negative():
    with pytest.raises(UserError, match=r"eval.interval=-1 is not valid; it must be >= 0 \(0: only the final"):
        relayrl.load_config("dqn", ["eval.interval=-1"])


@pytest.mark.parametrize("name", NAMES)
def test_metrics_rows_carry_the_schedules(runs, name):
    """Each evaluation row holds the agent's schedule values where the run was, as TensorBoard's
    charts/ does, so a plot of metrics.jsonl alone can show what the learning rate or epsilon was."""
    cfg, root = runs(name)
    rows = RunDir(root).read_metrics()
    if not algorithm(name).agent:  # BPTT's step-0 row comes before any iteration (and its learning rate)
        rows = rows[1:]
    assert all("charts/learning_rate" in r for r in rows)
    if name == "dqn":
        eps = [r["charts/epsilon"] for r in rows]
        assert eps[0] == cfg.agent.epsilon_start and eps == sorted(eps, reverse=True)
