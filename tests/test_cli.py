"""The `relayrl` command: bad input gives one line and exit 2; the quick start works."""

import json
import os
import subprocess
import sys

import pytest

RELAYRL = [sys.executable, "-m", "relayrl.cli"]


def run(args, env, cwd=None):
    return subprocess.run(RELAYRL + args, capture_output=True, text=True, env=env, cwd=cwd, timeout=300)


@pytest.mark.parametrize("args, fragment", [
    (["train", "no-such-preset"], "unknown preset 'no-such-preset' (valid: bptt-pendulum, "),
    (["train", "dqn-cartpole", "--set", "env.id=CartPool-v9"], "is not a registered Gymnasium id"),
    (["train", "dqn-cartpole", "--set", "agent.nope=1"], "unknown config key 'agent.nope'"),
    (["train", "dqn-cartpole", "--set", "train.total_steps=ten"], "expected int"),
    (["train", "dqn-cartpole", "--seed", "x"], "invalid int value"),
    (["train", "dqn-cartpole", "--seed", "-3"], "argument --seed: -3 is not valid; it must be an integer in [0, 9223"),
    (["train", "missing.toml"], "config file 'missing.toml' does not exist"),
    (["eval", "/no/such/run"], "run directory '/no/such/run' does not exist"),
    (["plot", "/no/such/run"], "does not exist"),
    (["plot", __file__], "is a file, not a run directory"),
    (["video", "/no/such/run"], "does not exist"),
    (["train", "dqn-cartpole", "--resume"], "--resume needs --run-dir"),
    (["train", "dqn-cartpole", "--run-dir", "r", "--resume", "--overwrite"], "--overwrite replaces a run, --resume "
                                                                             "continues it: pass one of them"),
    (["train", "dqn-cartpole", "--seed", "5", "--set", "seed=7"], "--seed 5 and --set seed=7 name two seeds"),
    (["train", "dqn-cartpole", "--set", "env.id=mymod.MyEnv"], "did you mean mymod:MyEnv?"),
    (["train", "sac", "--set", "env.id=HalfCheetah-v3"], "env.id='HalfCheetah-v3' could not be made: ImportError: "
                                                         "The mujoco v2 and v3 based environments have been moved"),
    (["train", "sac", "--set", "env.id=HalfCheetah-v3"], "; HalfCheetah-v5 is this env's newest version"),
    (["train"], "train needs PRESET|CONFIG.toml (see `relayrl presets`), or --run-dir DIR --resume"),
    (["frobnicate"], "invalid choice"),
    (["train", "dqn-cartpole", "--dir", "x"], "unrecognized arguments: --dir x; did you mean --run-dir?"),
    (["train", "dqn-cartpole", "--foo"], "unrecognized arguments: --foo (see 'relayrl train --help')"),
    (["plot", "x", "--episodes", "3"], "unrecognized arguments: --episodes 3 (see 'relayrl plot --help')"),  # eval's
    # CleanRL's and SB3's flags: the --set that gives them
    (["train", "ppo", "--env-id", "CartPole-v1"], "unrecognized arguments: --env-id CartPole-v1; relayrl takes "
     "settings as --set KEY=VALUE (--set env.id=CartPole-v1): CleanRL's env_id is env.id"),
    (["train", "ppo", "--total-timesteps=10000"], "(--set train.total_steps=10000): Stable-Baselines3's "
                                                  "total_timesteps is train.total_steps"),
    (["train", "ppo", "--cuda", "false"], "relayrl takes settings as --set KEY=VALUE: CleanRL's cuda is device"),
    (["config", "ppo", "--seed", "1"], "unrecognized arguments: --seed 1; this command takes it as --set seed=1"),
    (["config", "ppo", "--set", "vf_coef=0.5"], "did you mean 'agent.vf_coef'? (keys sit in their sections); "
                                                "CleanRL's vf_coef is agent.vf_coef at half CleanRL's value"),
    (["train", "dqn", "--set", "train.total_steps", "100"], "--set train.total_steps 100: --set takes KEY=VALUE as "
                                                            "one word (--set train.total_steps=100)"),
    (["config", "dqn", "--set", "agent.lr", "0.1"], "(--set agent.lr=0.1)"),
    (["train", "--set", "agent.lr", "0.1", "dqn"], "--set agent.lr 0.1: --set takes KEY=VALUE"),  # 0.1: the preset
    (["train", "--set", "train.total_steps", "10"], "--set train.total_steps 10: --set takes KEY=VALUE"),  # no preset
])
def test_bad_input_is_one_line_and_exit_2(args, fragment, cli_env, tmp_path):
    r = run(args, cli_env, cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("relayrl: error:"), r.stderr
    assert fragment in lines[0]
    assert "Traceback" not in r.stderr
    assert not (tmp_path / "runs").exists()  # nothing written for bad input


def test_running_out_of_memory_during_a_run_is_one_line(cli_env, tmp_path):
    huge = "100000000000000"  # PPO allocates its rollout once the run has started (and evaluated step 0)
    r = run(["train", "ppo-cartpole", "--run-dir", str(tmp_path / "r"), "--no-progress", "--set",
             f"train.collect_steps={huge}", "--set", f"train.total_steps={huge}"], cli_env)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("relayrl: error: out of memory (Unable to allocate")


def test_video_help_names_every_format_it_writes():
    from relayrl.cli import build_parser
    from relayrl.video import VIDEO_SUFFIXES

    text = build_parser().parse_args(["video", "r"]).parsers["video"].format_help()
    assert all(suffix in text for suffix in VIDEO_SUFFIXES), text


def test_presets_lists_one_per_line(cli_env):
    r = run(["presets"], cli_env)
    assert r.returncode == 0
    names = [line.split("\t")[0] for line in r.stdout.splitlines()]
    assert "dqn-cartpole" in names and "dqn-cartpole-fast" in names


def test_existing_run_is_never_overwritten(cli_env, tmp_path):
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "metrics.jsonl").write_text('{"step": 1}\n')
    r = run(["train", "dqn-cartpole", "--run-dir", str(tmp_path / "run")], cli_env)
    assert r.returncode == 2 and "already holds a run" in r.stderr
    assert (tmp_path / "run" / "metrics.jsonl").read_text() == '{"step": 1}\n'


def test_quick_start_commands_at_small_size(cli_env, tmp_path):
    """The README's train command, shrunk: train, plot, video, eval on one run directory."""
    rd = str(tmp_path / "quick")
    r = run(["train", "dqn-cartpole-fast", "--run-dir", rd, "--set", "train.total_steps=1200",
             "--set", "eval.interval=600", "--set", "eval.episodes=2", "--set", "train.initial_collect_steps=100",
             "--set", "train.collect_steps=100", "--set", "train.gradient_steps=10", "--no-progress"], cli_env)
    assert r.returncode == 0, r.stderr
    for name in ("config.toml", "metrics.jsonl", "tb", "checkpoints", "policy/policy.pt"):
        assert (tmp_path / "quick" / name).exists(), name
    rows = [json.loads(line) for line in (tmp_path / "quick" / "metrics.jsonl").read_text().splitlines()]
    assert [row["step"] for row in rows] == [0, 600, 1200]
    for key in ("step", "train_step", "average_return", "average_episode_length", "wall_time_s"):
        assert key in rows[-1]
    assert run(["plot", rd], cli_env).returncode == 0
    assert (tmp_path / "quick" / "returns.png").stat().st_size > 1000
    v = run(["video", rd, "--out", str(tmp_path / "a.mp4")], cli_env)
    assert v.returncode == 0, v.stderr
    assert (tmp_path / "a.mp4").read_bytes()[4:8] == b"ftyp"  # an MP4 container
    e = run(["eval", rd, "--episodes", "3"], cli_env)
    assert e.returncode == 0, e.stderr
    result = json.loads(e.stdout)
    assert result["episodes"] == 3 and result["average_return"] > 0
    e = run(["eval", str(tmp_path / "quick" / "policy" / "policy.pt"), "--episodes", "3"], cli_env)  # as --help says
    assert e.returncode == 0 and json.loads(e.stdout) == result, e.stderr


@pytest.mark.parametrize("example, args, said", [
    ("dqn_cartpole.py", ["--iterations", "300", "--eval-interval", "300"], "iteration 300: eval return"),
    ("sac_actor_learner.py", ["--iterations", "100", "--initial-steps", "100", "--eval-interval", "50", "--hidden",
                              "32", "--batch-size", "32", "--out", "{tmp}/out"], "train step 100: eval return"),
    ("ppo_cartpole.py", ["--iterations", "2", "--eval-interval", "2"], "iteration 2 (512 env steps): eval return"),
])
def test_each_example_runs_a_few_hundred_steps(cli_env, tmp_path, example, args, said):
    """DESIGN.md: one readable single-file example per algorithm, run by CI for a few hundred steps."""
    import pathlib

    path = pathlib.Path(__file__).parents[1] / "examples" / example
    r = subprocess.run([sys.executable, str(path), *(a.format(tmp=tmp_path) for a in args)],
                       capture_output=True, text=True, env=cli_env, timeout=300)
    assert r.returncode == 0, r.stderr
    assert said in r.stdout


def test_ci_runs_the_readme_test_command():
    import pathlib

    root = pathlib.Path(__file__).parents[1]
    ci = (root / ".ci" / "run").read_text().strip().splitlines()[-1]
    assert ci in (root / "README.md").read_text()


def test_a_shared_policy_file_evaluates_on_its_runs_env_kwargs_and_time_limit_but_runs_no_code(tmp_path, capsys,
                                                                                              monkeypatch):
    import shutil

    import relayrl
    from relayrl.cli import main
    from relayrl.policy_file import load_policy_file, save_policy_file

    short = ["train.total_steps=60", "train.initial_collect_steps=20", "eval.interval=60", "eval.episodes=1",
             "agent.batch_size=8"]
    cfg = relayrl.load_config("dqn-cartpole", [*short, "env.id=FrozenLake-v1", "env.kwargs={map_name = '8x8'}",
                                               "env.max_episode_steps=5"])
    relayrl.train(cfg, tmp_path / "run", progress=False)
    capsys.readouterr()
    shared = tmp_path / "policy.pt"
    shutil.copy(tmp_path / "run" / "policy" / "policy.pt", shared)
    policy = relayrl.load_policy(shared)
    assert (policy.env_kwargs, policy.max_episode_steps) == ({"map_name": "8x8"}, 5)
    assert main(["eval", str(shared), "--episodes", "2"]) == 0  # Discrete(64): the 8x8 map, cut at 5 steps
    assert json.loads(capsys.readouterr().out)["average_episode_length"] <= 5.0
    # --env naming the id the file records gets its kwargs and time limit (the 4x4 default would not fit)
    assert main(["eval", str(shared), "--env", "FrozenLake-v1", "--episodes", "2"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["average_episode_length"] <= 5.0
    assert "FrozenLake-v1 is the env the policy was trained on: env.kwargs {'map_name': '8x8'} and " \
           "env.max_episode_steps=5 apply" in err
    assert relayrl.evaluate(policy, "FrozenLake-v1", episodes=2) == relayrl.evaluate(policy, episodes=2)
    import relayrl.export as export

    loads = []
    real = export.load_policy
    monkeypatch.setattr(export, "load_policy", lambda *a, **k: loads.append(a) or real(*a, **k))
    assert relayrl.evaluate(shared, episodes=2) == relayrl.evaluate(policy, episodes=2)
    assert len(loads) == 1  # the lone file is read once: for its env record and to act
    state = load_policy_file(shared)
    for name, changes in (("anonymous", {"env_id": None}), ("code", {"env_id": "os:system",
                                                                      "env_kwargs": {"command": "true"}}),
                          ("wrapped", {"env_wrappers": ["os:getcwd"]})):
        save_policy_file({**state, **changes}, tmp_path / f"{name}.pt")
        assert main(["eval", str(tmp_path / f"{name}.pt")]) == 2
        said = capsys.readouterr().err
        assert ("records no env id" if name == "anonymous" else "would import and run code it names") in said
        assert "give the env to evaluate on (--env ENV_ID; in Python, env=)" in said
    with pytest.raises(relayrl.errors.UserError, match=r"would import and run code it names \(os:system\)"):
        relayrl.evaluate(tmp_path / "code.pt")


def test_eval_of_a_policy_file_outside_a_run_directory_uses_the_env_it_records(tmp_path, capsys):
    import shutil

    import relayrl
    from relayrl.cli import main

    (tmp_path / "policy.pt").write_bytes(b"not used")
    assert main(["eval", str(tmp_path / "policy.pt")]) == 2
    err = capsys.readouterr().err
    assert "is not a relayrl policy file" in err and len(err.strip().splitlines()) == 1
    cfg = relayrl.load_config("dqn-cartpole", ["train.total_steps=60", "train.initial_collect_steps=20",
                                               "eval.interval=60", "eval.episodes=1", "agent.batch_size=8"])
    relayrl.train(cfg, tmp_path / "run", progress=False)
    capsys.readouterr()
    shared = tmp_path / "shared dir" / "cart pole.pt"  # the file a run shares, on its own
    shared.parent.mkdir()
    shutil.copy(tmp_path / "run" / "policy" / "policy.pt", shared)
    assert relayrl.load_policy(shared).env_id == "CartPole-v0"  # dqn-cartpole's, TF-Agents' tutorial env
    assert main(["eval", str(shared), "--episodes", "2"]) == 0
    assert json.loads(capsys.readouterr().out)["episodes"] == 2
    assert main(["eval", str(shared), "--episodes", "1", "--env", "CartPole-v1"]) == 0  # another env, same spaces
    assert capsys.readouterr().err == "relayrl: the policy was trained on CartPole-v0, evaluated here on CartPole-v1\n"
    assert main(["eval", str(tmp_path / "run"), "--episodes", "1", "--env", "Acrobot-v1"]) == 2  # 6 obs, not 4
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert "do not fit the policy (trained on CartPole-v0)" in err
    assert main(["eval", str(shared), "--episodes", "2", "--max-episode-steps", "3"]) == 0  # episodes cut at 3
    assert json.loads(capsys.readouterr().out)["average_episode_length"] == 3.0
    assert main(["eval", str(shared), "--max-episode-steps", "0"]) == 2
    assert "--max-episode-steps 0 is not valid; it must be >= 1" in capsys.readouterr().err


def test_eval_reads_the_policy_file_it_is_given(tmp_path, capsys):
    import relayrl
    from relayrl.cli import main

    cfg = relayrl.load_config("dqn-cartpole", ["train.total_steps=60", "train.initial_collect_steps=20",
                                               "eval.interval=60", "eval.episodes=1", "agent.batch_size=8"])
    relayrl.train(cfg, tmp_path / "run", progress=False)
    (tmp_path / "run" / "policy" / "other.pt").write_bytes(b"not a policy")
    assert main(["eval", str(tmp_path / "run" / "policy" / "other.pt"), "--episodes", "1"]) == 2  # not policy.pt
    assert main(["eval", str(tmp_path / "run" / "policy"), "--episodes", "1"]) == 0  # the folder names its run
    assert main(["eval", str(tmp_path / "run" / "config.toml"), "--episodes", "1"]) == 0


def test_ctrl_c_outside_a_run_says_interrupted_and_inside_one_that_nothing_is_lost(monkeypatch, tmp_path, capsys):
    from relayrl import cli
    from relayrl.training.run_dir import RunDir

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "_eval", interrupted)
    assert cli.main(["eval", str(tmp_path)]) == 130
    assert capsys.readouterr().err == "relayrl: interrupted\n"
    # Ctrl-C while torch is still importing (the run directory cannot be looked at): one line
    monkeypatch.setattr(cli, "_train", interrupted)
    monkeypatch.setattr(RunDir, "has_checkpoint", lambda self: torch_half_imported())
    assert cli.main(["train", "dqn", "--run-dir", str(tmp_path / "r")]) == 130
    assert capsys.readouterr().err.startswith("relayrl: interrupted before the first checkpoint: nothing to resume")


def test_ctrl_c_after_a_run_reached_its_end_does_not_offer_resume(monkeypatch, tmp_path, capsys):
    """A Ctrl-C in the last moments, after the end's checkpoint and evaluation were written: a
    --resume would find nothing left to do."""
    from relayrl import cli

    run = tmp_path / "r"
    tiny = ["--set", "train.total_steps=300", "--set", "train.initial_collect_steps=100", "--set", "eval.interval=150",
            "--set", "eval.episodes=1", "--set", "env.id=CartPole-v1"]
    assert cli.main(["train", "dqn", "--run-dir", str(run), "--no-progress", *tiny]) == 0
    capsys.readouterr()

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "_train", interrupted)
    assert cli.main(["train", "dqn", "--run-dir", str(run), "--resume"]) == 130
    assert capsys.readouterr().err == (f"relayrl: interrupted after the run reached its end and evaluated it: it is "
                                       f"complete in {run}\n")
    # a resume that extends the run, or a run that replaces it, did not reach the end it asks for
    assert cli.main(["train", "dqn", "--run-dir", str(run), "--resume", "--set", "train.total_steps=5000"]) == 130
    assert "resume with --resume from the last checkpoint" in capsys.readouterr().err
    assert cli.main(["train", "dqn", "--run-dir", str(run), "--overwrite", *tiny]) == 130
    assert "resume with --resume from the last checkpoint" in capsys.readouterr().err
    rows = (run / "metrics.jsonl").read_text().splitlines()
    (run / "metrics.jsonl").write_text("\n".join(rows[:-1]) + "\n")  # its final evaluation not written yet
    assert cli.main(["train", "dqn", "--run-dir", str(run), "--resume"]) == 130
    assert "resume with --resume from the last checkpoint" in capsys.readouterr().err


def torch_half_imported():
    raise AttributeError("partially initialized module 'torch' has no attribute 'distributed'")


# Stands for torch left half-imported by a Ctrl-C: importing it again raised (or crashed the process).
_HALF_IMPORTED_TORCH = """
import sys
class HalfImported:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] == "torch":
            raise RuntimeError("duplicate registrations for aten.linspace.Tensor_Tensor")
sys.meta_path.insert(0, HalfImported())
from relayrl import cli
def interrupted(args):
    raise KeyboardInterrupt
cli._train = interrupted
sys.exit(cli.main(sys.argv[1:]))
"""


@pytest.mark.parametrize("files, line", [
    ({"checkpoints/ckpt-000000001000.pt": ""}, "interrupted; resume with --resume from the last checkpoint"),
    ({"metrics.jsonl": '{"step": 0}\n{"step": 500}\n'}, "interrupted before the first checkpoint: nothing to "
                                                        "resume; the policy and metrics so far stay in"),
])
def test_ctrl_c_while_torch_imports_reads_the_run_dir_without_torch(files, line, cli_env, tmp_path):
    run_dir = tmp_path / "run"
    for name, text in {"config.toml": "", **files}.items():
        (run_dir / name).parent.mkdir(parents=True, exist_ok=True)
        (run_dir / name).write_text(text)
    r = subprocess.run([sys.executable, "-c", _HALF_IMPORTED_TORCH, "train", "--run-dir", str(run_dir), "--resume"],
                       capture_output=True, text=True, env=cli_env, timeout=60)
    assert (r.returncode, r.stderr.startswith(f"relayrl: {line}")) == (130, True), r.stderr


def test_eval_stochastic_samples_the_policy_repeatably(tmp_path, capsys):
    import relayrl
    from relayrl.cli import main

    cfg = relayrl.load_config("ppo", ["env.id=Pendulum-v1", "train.total_steps=256", "train.collect_steps=128",
                                      "agent.batch_size=64", "eval.interval=0", "eval.episodes=1",
                                      "env.max_episode_steps=20", "train.torch_threads=1"])
    relayrl.train(cfg, tmp_path / "run", progress=False)
    capsys.readouterr()
    results = []
    for flags in ([], ["--stochastic"], ["--stochastic"], ["--stochastic", "--seed", "1"]):
        assert main(["eval", str(tmp_path / "run"), "--episodes", "2", *flags]) == 0
        results.append(json.loads(capsys.readouterr().out)["average_return"])
    mean, sampled, again, other_seed = results
    assert sampled == again and sampled != mean and other_seed != sampled


def test_a_windows_style_run_dir_gets_a_note_on_posix():
    """`--run-dir runs\\lab1` on Linux is one folder named with a backslash, not lab1 in runs."""
    from relayrl.cli import backslash_note

    assert backslash_note("runs/lab1") is None
    if sys.platform != "win32":
        note = backslash_note("C:\\Users\\me\\lab1")
        assert note is not None and "--run-dir 'C:\\Users\\me\\lab1' has a backslash" in note
        assert "write 'C:/Users/me/lab1' for nested folders" in note


def test_a_sigterm_that_ray_turned_into_a_plain_keyboard_interrupt_still_exits_143(monkeypatch, capsys):
    """Ray's blocking calls catch the Terminated that the SIGTERM handler raised in them and raise
    a plain KeyboardInterrupt: the run was still terminated, and says so as a kill (143), not as
    Ctrl-C (130)."""
    import signal

    from relayrl import cli

    def train_inside_ray_get(args):
        try:
            cli._on_sigterm(signal.SIGTERM, None)
        except KeyboardInterrupt:
            raise KeyboardInterrupt from None  # what ray.get raises

    monkeypatch.setattr(cli, "_train", train_inside_ray_get)
    assert cli.main(["train", "dqn-cartpole"]) == 143
    assert "relayrl: terminated" in capsys.readouterr().err
    monkeypatch.setattr(cli, "_train", lambda args: (_ for _ in ()).throw(KeyboardInterrupt))  # Ctrl-C
    assert cli.main(["train", "dqn-cartpole"]) == 130


def test_eval_on_a_named_env_applies_a_run_directorys_wrappers_and_a_policy_files_when_trusted(tmp_path, capsys):
    """env.wrappers are the policy's input: `relayrl eval RUN --env ID` applies a run's (its
    config.toml imports them anyway), over its own id or another; a policy file on its own runs
    no code unless --trust-code."""
    import shutil

    import relayrl
    from relayrl.cli import main

    short = ["train.total_steps=60", "train.initial_collect_steps=20", "eval.interval=60", "eval.episodes=1",
             "agent.batch_size=8", "env.id=toy_envs:Countdown", "env.wrappers=['toy_envs:double_reward']"]
    relayrl.train(relayrl.load_config("dqn-cartpole", short), tmp_path / "run", progress=False)
    capsys.readouterr()
    assert main(["eval", str(tmp_path / "run"), "--env", "toy_envs:Countdown", "--episodes", "1"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["average_return"] == 6.0  # 3 steps, rewards doubled
    assert "env.wrappers ['toy_envs:double_reward'] applies" in err
    assert main(["eval", str(tmp_path / "run"), "--env", "toy_envs:make_countdown", "--episodes", "1"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["average_return"] == 6.0
    assert ("the policy was trained on toy_envs:Countdown, evaluated here on toy_envs:make_countdown: env.wrappers "
            "['toy_envs:double_reward'] applies") in err
    shutil.copy(tmp_path / "run" / "policy" / "policy.pt", tmp_path / "policy.pt")
    assert main(["eval", str(tmp_path / "policy.pt"), "--env", "toy_envs:Countdown", "--episodes", "1"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["average_return"] == 3.0 and "from its run directory, or with --trust-code, they do" in err
    assert main(["eval", str(tmp_path / "policy.pt"), "--env", "toy_envs:Countdown", "--episodes", "1",
                 "--trust-code"]) == 0
    assert json.loads(capsys.readouterr().out)["average_return"] == 6.0
    assert relayrl.evaluate(tmp_path / "run", "toy_envs:Countdown", episodes=1).mean == 6.0  # in Python too


def test_the_current_directory_goes_last_on_the_import_path(tmp_path, monkeypatch, capsys):
    """A user's env module in their project folder is found; a folder there that shares a name
    with a module a library tries to import (torch.export's optional z3) does not shadow it."""
    from relayrl import cli

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", str(tmp_path))])
    assert cli.main(["presets"]) == 0
    assert sys.path[-1] == str(tmp_path)


def test_a_resume_naming_its_preset_without_a_seed_keeps_the_runs_seed(tmp_path, capsys):
    """`relayrl train PRESET --run-dir R --resume` compared the preset's seed (0) with the run's
    and refused a run started with --seed 1; a seed given on the resume is still checked."""
    from relayrl import cli

    run, small = str(tmp_path / "r"), ["--set", "train.total_steps=300", "--set", "train.initial_collect_steps=100",
                                       "--no-progress"]
    assert cli.main(["train", "dqn-cartpole-fast", "--run-dir", run, "--seed", "1", *small]) == 0
    longer = ["--set", "train.total_steps=400", "--no-progress"]
    assert cli.main(["train", "dqn-cartpole-fast", "--run-dir", run, "--resume", *longer]) == 0
    assert "final evaluation" in capsys.readouterr().out
    for seeded in (["--seed", "2"], ["--set", "seed=2"]):
        assert cli.main(["train", "dqn-cartpole-fast", "--run-dir", run, "--resume", *seeded, *longer]) == 2
        assert "--resume: seed=2 but the run in" in capsys.readouterr().err


@pytest.mark.parametrize("closed", ["stdout", "stderr"])
def test_a_command_whose_output_was_closed_at_start_runs(closed):
    """`relayrl presets >&-` (a daemon's closed descriptor): Python's sys.stdout is None, which
    print() writes nothing to; wrapping it for a reader gone made every command fail."""
    fd = 1 if closed == "stdout" else 2
    r = subprocess.run(RELAYRL + ["presets"], pass_fds=(), timeout=120,
                       preexec_fn=lambda: os.close(fd), capture_output=False,
                       stdout=subprocess.DEVNULL if fd == 2 else None, stderr=subprocess.DEVNULL if fd == 1 else None)
    assert r.returncode == 0
    bad = subprocess.run(RELAYRL + ["train", "nosuch"], timeout=120, preexec_fn=lambda: os.close(fd),
                         stdout=subprocess.DEVNULL if fd == 2 else None, stderr=subprocess.DEVNULL if fd == 1 else None)
    assert bad.returncode == 2


def test_a_policy_file_that_is_not_there_is_named_as_one(tmp_path, capsys):
    from relayrl.cli import main

    best = str(tmp_path / "run" / "policy" / "best.pt")
    assert main(["eval", best]) == 2
    assert capsys.readouterr().err.strip() == (f"relayrl: error: policy file {best!r} does not exist (runs made "
                                               "before eval.keep_best have no policy/best.pt)")


def test_text_the_output_encoding_cannot_spell_is_written_escaped():
    """A run directory named in Chinese, printed to a file redirected under Windows' cp1252: the
    run had trained and saved, then the command failed on its last line."""
    import io

    from relayrl.streams import PipeSafe

    raw = io.BytesIO()
    stream = PipeSafe(io.TextIOWrapper(raw, encoding="cp1252"))
    stream.write("run directory: runs/\u8bad\u7ec3 caf\u00e9\n")
    stream.flush()
    assert raw.getvalue().decode("cp1252") == "run directory: runs/\\u8bad\\u7ec3 caf\u00e9\n"


_CTRL_C_IN_TORCHS_IMPORT = """
import os, signal, sys
class CtrlC:  # a notebook's interrupt while torch.fx is being imported
    def find_spec(self, name, path=None, target=None):
        if name == "torch.fx":
            sys.meta_path.remove(self)
            os.kill(os.getpid(), signal.SIGINT)
sys.meta_path.insert(0, CtrlC())
import relayrl
try:
    relayrl.train
except KeyboardInterrupt:
    print("interrupted", file=sys.stderr)
relayrl.train(relayrl.load_config("dqn-cartpole", ["train.total_steps=100", "train.initial_collect_steps=50",
                                                   "eval.episodes=1"]), sys.argv[1], progress=False)
print("trained")
"""


def test_ctrl_c_while_torch_is_first_imported_leaves_it_whole_for_the_next_call(cli_env, tmp_path):
    """A notebook's first `relayrl.train` interrupted in torch's import: the next call segfaulted or
    met 'partially initialized module torch'."""
    r = subprocess.run([sys.executable, "-c", _CTRL_C_IN_TORCHS_IMPORT, str(tmp_path / "run")], capture_output=True,
                       text=True, env=cli_env, timeout=120)
    assert r.returncode == 0 and r.stdout == "trained\n", r.stderr
    assert r.stderr.startswith("relayrl: stopping once the import of torch is complete (one cut short breaks it in "
                               "this process)\ninterrupted\n"), r.stderr


@pytest.mark.parametrize("words, said", [
    ("train.total_steps 2000", "--set train.total_steps 2000: --set takes KEY=VALUE as one word "
                               "(--set train.total_steps=2000)"),
    ("train.total_steps = 2000", "--set train.total_steps = 2000: --set takes KEY=VALUE as one word "
                                 "(--set train.total_steps=2000)"),
    ("train.total_steps =2000", "--set train.total_steps =2000: --set takes KEY=VALUE as one word "
                                "(--set train.total_steps=2000)"),
    ("train.total_steps= 2000", "--set train.total_steps= 2000: --set takes KEY=VALUE as one word "
                                "(--set train.total_steps=2000)"),
    ("agent.hidden=[128 64]", "--set agent.hidden=[128 64]: the shell split the list at its spaces; quote it, with "
                              "commas between the entries (--set 'agent.hidden=[128, 64]')"),
])
def test_a_set_the_shell_split_into_words_says_the_one_word_meant(words, said, tmp_path, capsys):
    """`= 2000` was answered --set train.total_steps==, and `[128 128]` unquoted 'unrecognized arguments: 128]'."""
    from relayrl.cli import main

    assert main(["train", "dqn-cartpole-fast", "--run-dir", str(tmp_path / "r"), "--set", *words.split()]) == 2
    assert capsys.readouterr().err == f"relayrl: error: {said}\n"
    assert not (tmp_path / "r").exists()


def test_an_empty_value_before_another_set_is_a_value_not_a_split_word(tmp_path, capsys):
    from relayrl.cli import main

    args = ["config", "dqn-cartpole-fast", "--set", "distributed.address=", "--set", "train.total_steps=100"]
    assert main(args) == 0 and "total_steps = 100" in capsys.readouterr().out
