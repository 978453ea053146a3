"""policy.pt is read without running code: crafted files are refused, every algorithm's still loads."""

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

import relayrl
from relayrl.errors import UserError
from relayrl.policy_file import REFUSED

RELAYRL = [sys.executable, "-m", "relayrl.cli"]
TINY = {
    "dqn": ("dqn-cartpole-fast", ["train.total_steps=300", "train.initial_collect_steps=100", "eval.interval=300",
                                  "eval.episodes=1", "train.collect_steps=100", "train.gradient_steps=5",
                                  "agent.hidden=[16,16]"], (4,)),
    "sac": ("sac-pendulum", ["train.total_steps=300", "train.initial_collect_steps=100", "eval.interval=300",
                             "eval.episodes=1", "agent.actor_hidden=[16,16]", "agent.critic_hidden=[16,16]",
                             "agent.batch_size=16"], (3,)),
    "bptt": ("bptt-pendulum", ["train.total_steps=3200", "eval.interval=3200"], (3,)),
}


class _Payload:
    """Unpickling this runs `touch <marker>`: what a crafted policy file would do."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    for algo, (preset, overrides, _) in TINY.items():
        relayrl.train(relayrl.load_config(preset, overrides, seed=0), root / algo, progress=False)
    return root


@pytest.mark.parametrize("algo", sorted(TINY))
def test_every_algorithms_policy_file_is_plain_data(runs, algo):
    # weights_only=True with no extra globals: tensors, numbers, strings, lists and dicts only
    state = torch.load(runs / algo / "policy" / "policy.pt", weights_only=True)
    assert state["kind"] in ("q_greedy", "tanh_gaussian", "clamped_mlp")
    obs = torch.randn(5, *TINY[algo][2])
    assert relayrl.load_policy(runs / algo)(obs).shape[0] == 5


def test_a_policy_saved_with_numpy_bounds_still_loads_and_acts_the_same(runs, tmp_path):
    state = torch.load(runs / "sac" / "policy" / "policy.pt", weights_only=True)
    old = {**state, "action_low": np.asarray(state["action_low"], np.float32),
           "action_high": np.asarray(state["action_high"], np.float32)}
    torch.save(old, tmp_path / "policy.pt")  # the layout an earlier release wrote
    obs = torch.randn(7, 3)
    assert torch.equal(relayrl.load_policy(tmp_path / "policy.pt")(obs), relayrl.load_policy(runs / "sac")(obs))


@pytest.fixture
def crafted_run(runs, tmp_path):
    """A copy of a real run whose policy.pt carries a payload; returns (run dir, marker path)."""
    run = tmp_path / "shared-run"
    shutil.copytree(runs / "dqn", run)
    marker = tmp_path / "code-ran"
    state = torch.load(run / "policy" / "policy.pt", weights_only=True)
    torch.save({**state, "hidden": _Payload(marker)}, run / "policy" / "policy.pt")
    return run, marker


def test_load_policy_refuses_a_file_that_would_run_code(crafted_run):
    run, marker = crafted_run
    for target in (run, run / "policy" / "policy.pt"):
        with pytest.raises(UserError, match=REFUSED):
            relayrl.load_policy(target)
        with pytest.raises(UserError, match=REFUSED):
            relayrl.export_policy(target)
    assert not marker.exists()


@pytest.mark.parametrize("command", [["eval"], ["video"], ["export"]])
def test_the_cli_refuses_it_in_one_line(crafted_run, command, cli_env, tmp_path):
    run, marker = crafted_run
    r = subprocess.run(RELAYRL + [*command, str(run)], capture_output=True, text=True, env=cli_env, cwd=tmp_path,
                       timeout=300)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and REFUSED in lines[0] and "Traceback" not in r.stderr, r.stderr
    assert not marker.exists()
    assert not (run / "policy" / "policy.pt2").exists() and not list(run.glob("*.mp4"))


@pytest.mark.parametrize("content", [
    torch.zeros(3),  # not a dict
    {"weights": torch.zeros(3)},  # another program's dict: it was called a policy of an unknown kind
    {"kind": "q_greedy", "obs_dim": 4},  # keys missing
    {"kind": "q_greedy", "obs_dim": 4, "hidden": [8], "num_actions": 2, "activation": "relu",
     "state_dict": {"layers.0.weight": torch.zeros(8, 3)}},  # weights of the wrong shape
], ids=["tensor", "no-kind", "missing-keys", "wrong-shapes"])
def test_plain_files_that_are_not_policies_are_one_line_errors(tmp_path, content):
    torch.save(content, tmp_path / "policy.pt")
    with pytest.raises(UserError, match=REFUSED):
        relayrl.load_policy(tmp_path / "policy.pt")


def test_a_file_that_is_not_a_torch_file_is_one_line_error(tmp_path):
    (tmp_path / "policy.pt").write_bytes(b"not a policy")
    with pytest.raises(UserError, match=r"is not a relayrl policy file \(not a file torch.save wrote\)"):
        relayrl.load_policy(tmp_path / "policy.pt")
    (tmp_path / "notes.txt").write_text("hi\n")  # torch's KeyError: 105 ('i')
    with pytest.raises(UserError, match=r"'.*notes.txt' is not a relayrl policy file \(not a file torch.save wrote\): "
                                        r"give a run directory or its policy/policy.pt$"):
        relayrl.load_policy(tmp_path / "notes.txt")
    torch.save({"kind": "q_greedy", "x": torch.zeros(1000)}, tmp_path / "whole.pt")
    (tmp_path / "policy.pt").write_bytes((tmp_path / "whole.pt").read_bytes()[:2000])  # a write cut short
    with pytest.raises(UserError, match=r"is unreadable \(RuntimeError: PytorchStreamReader failed reading zip "
                                        r"archive: failed finding central directory\): damaged, or not a relayrl"):
        relayrl.load_policy(tmp_path / "policy.pt")


def test_a_policy_file_whose_bytes_changed_is_refused_in_one_line(runs, tmp_path):
    source = runs / "dqn" / "policy" / "policy.pt"
    data = bytearray(source.read_bytes())
    weights = torch.load(source, weights_only=True)["state_dict"]
    first = next(iter(weights.values()))
    at = data.find(first.numpy().tobytes())
    data[at + 3] ^= 0x01  # bit rot, or a copy gone wrong
    (tmp_path / "policy.pt").write_bytes(bytes(data))
    with pytest.raises(UserError, match=r"^policy file '.*policy.pt' is damaged: its bytes changed after it was "
                                        r"written \(BadZipFile: Bad CRC-32 for file '.*'\); copy it again from "
                                        r"where it came from$"):
        relayrl.load_policy(tmp_path / "policy.pt")


def test_a_byte_changed_anywhere_in_a_policy_file_is_one_line(runs, tmp_path):
    """A flip in the zip's own directory escaped the check as UnicodeDecodeError, NotImplementedError
    ('zip file version'), RuntimeError ('encrypted'), zlib.error or OSError tracebacks."""
    data = (runs / "dqn" / "policy" / "policy.pt").read_bytes()
    path = tmp_path / "policy.pt"
    for at in range(len(data) - 600, len(data), 3):  # the central directory and its end record
        for bit in (0x01, 0x80):
            changed = bytearray(data)
            changed[at] ^= bit
            path.write_bytes(bytes(changed))
            try:
                relayrl.load_policy(path)
            except UserError:
                pass


def test_a_stable_baselines3_model_file_says_how_to_evaluate_it(tmp_path):
    import zipfile

    with zipfile.ZipFile(tmp_path / "ppo_cartpole.zip", "w") as z:  # SB3's model.save() layout
        z.writestr("data", "{}")
        z.writestr("policy.pth", b"weights")
        z.writestr("_stable_baselines3_version", "2.4.0")
    with pytest.raises(UserError, match=r"is a Stable-Baselines3 model file, which relayrl does not read: in "
                                        r"Python, load it with SB3 .* relayrl.evaluate"):
        relayrl.load_policy(tmp_path / "ppo_cartpole.zip")


@pytest.mark.parametrize("fmt, run", [("pt2", r"torch\.export\.load\(path\)\.module\(\)"),
                                      ("onnx", r"onnxruntime\.InferenceSession\(path\)")], ids=["pt2", "onnx"])
def test_an_exported_program_given_as_a_policy_says_how_to_run_it(runs, tmp_path, fmt, run):
    if fmt == "onnx":
        pytest.importorskip("onnxscript")
    path = relayrl.export_policy(runs / "dqn", out=tmp_path / f"policy.{fmt}")
    with pytest.raises(UserError, match=rf"is a program written by relayrl export, not a policy file: run it "
                                        rf"with {run}; relayrl.load_policy, .* take the run directory"):
        relayrl.load_policy(path)  # was "damaged" (pt2) or "one that would run code" (onnx)


def test_a_checkpoint_given_as_a_policy_is_named_as_one_and_not_read(runs, tmp_path):
    marker = tmp_path / "ran"
    torch.save({"env": _Payload(marker)}, tmp_path / "ckpt-000000000300.pt")  # checkpoints hold pickles
    with pytest.raises(UserError, match=r"is a training checkpoint \(what --resume reads\), not a policy file \(a "
                                        r"run keeps its latest policy in policy/policy.pt and its best "
                                        r"evaluation's in policy/best.pt\); "
                                        r"relayrl.load_policy, .* take the run directory or its policy/policy.pt"):
        relayrl.load_policy(tmp_path / "ckpt-000000000300.pt")
    assert not marker.exists()


def test_an_exports_signature_names_the_env_as_trained_and_comes_with_its_program(tmp_path):
    preset, overrides, _ = TINY["dqn"]
    config = relayrl.load_config(preset, [*overrides, "env.max_episode_steps=50",
                                          "env.kwargs={sutton_barto_reward = true}"], seed=0)
    relayrl.train(config, tmp_path / "run", progress=False)
    sig = json.loads(relayrl.export_policy(tmp_path / "run").with_suffix(".pt2.json").read_text())
    assert (sig["env_id"], sig["env_kwargs"], sig["max_episode_steps"]) == ("CartPole-v1",
                                                                            {"sutton_barto_reward": True}, 50)
    assert "env_wrappers" not in sig  # none given: no empty entry
    (tmp_path / "out" / "p.pt2.json").mkdir(parents=True)  # its signature cannot be written
    with pytest.raises(UserError, match=r"p.pt2.json"):
        relayrl.export_policy(tmp_path / "run", out=tmp_path / "out" / "p.pt2")
    assert not (tmp_path / "out" / "p.pt2").exists()  # no program without its signature
    with pytest.raises(UserError, match=r"^out=123 is not valid; give a file or folder path"):
        relayrl.export_policy(tmp_path / "run", out=123)
