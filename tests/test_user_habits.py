"""Habits a new user brings (issue 25): no tracebacks from user input, `relayrl config`, --version,
help everywhere, "did you mean", TensorBoard as CleanRL names it, progress lines without a terminal.
(Loaded policies with NumPy and the ONNX export: tests/test_conformance.py.)"""

from __future__ import annotations

import dataclasses
import re
import subprocess
import sys
import tomllib

import pytest

import relayrl
from relayrl.cli import build_parser, main
from relayrl.config import from_dict, to_dict
from relayrl.config_fields import commented_toml, meanings
from relayrl.errors import ConfigError, UserError

TINY = ["train.total_steps=300", "train.initial_collect_steps=100", "eval.interval=300", "eval.episodes=1",
        "train.log_interval=100", "agent.hidden=[8]"]
TINY_SET = [a for o in TINY for a in ("--set", o)]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("habits") / "run"
    relayrl.train(relayrl.load_config("dqn-cartpole-fast", TINY), root, progress=False)
    return root


def _python_wrong_type(tmp_path, run_dir):
    config = relayrl.load_config("dqn-cartpole-fast")
    with pytest.raises(ConfigError, match=r"train.total_steps='abc' has the wrong type; expected int"):
        config.train.total_steps = "abc"


def _python_mistyped_key(tmp_path, run_dir):
    config = relayrl.load_config("dqn-cartpole-fast")
    with pytest.raises(ConfigError, match=r"unknown config key 'train.total_step'; did you mean 'train.total_steps'"):
        config.train.total_step = 100
    with pytest.raises(ConfigError, match=r"did you mean 'agent.lr'"):
        config.agent.lrr = 0.1


EITHER = "created, or one line"  # the run succeeds, or says in one line why not

# Every item of the "No tracebacks from user input" list: CLI arguments (one line on
# stderr, exit 2) or a Python callable (a clear exception).
SEED_RANGE = "it must be an integer in [0, 9223372036854775807]"
CASES = [
    pytest.param(lambda tmp, run: ["train", "dqn-cartpole-fast", "--seed", "-1"], SEED_RANGE, id="seed -1"),
    pytest.param(lambda tmp, run: ["train", "dqn-cartpole-fast", "--seed", "99999999999999999999"],
                 SEED_RANGE, id="seed too large"),
    pytest.param(lambda tmp, run: ["train", "dqn-cartpole-fast", "--run-dir", str(run / "config.toml"), *TINY_SET],
                 "", id="run-dir on an existing file"),
    pytest.param(lambda tmp, run: ["train", "dqn-cartpole-fast", "--run-dir", "/proc/relayrl-no/run", *TINY_SET],
                 "", id="run-dir in an unwritable parent"),
    pytest.param(lambda tmp, run: ["train", "dqn-cartpole-fast", "--run-dir", str(run / "config.toml" / "sub"),
                                   *TINY_SET], "", id="run-dir under a file"),
    pytest.param(lambda tmp, run: ["train", "dqn-cartpole-fast", "--run-dir", str(tmp / "no" / "such" / "run"),
                                   *TINY_SET], EITHER, id="run-dir in a missing parent"),
    pytest.param(lambda tmp, run: ["plot", str(run), "--out", str(tmp / "new" / "folder" / "r.png")], None,
                 id="plot --out into a missing folder"),
    pytest.param(lambda tmp, run: ["video", str(run), "--out", str(tmp / "new" / "v.mp4")], None,
                 id="video --out into a missing folder"),
    pytest.param(lambda tmp, run: ["export", str(run), "--out", str(tmp / "new" / "p.pt2")], None,
                 id="export --out into a missing folder"),
    pytest.param(lambda tmp, run: ["plot", str(run), "--out", str(run / "config.toml" / "r.png")],
                 "cannot create the folder of --out", id="plot --out under a file"),
    pytest.param(lambda tmp, run: ["eval", str(run), "--seed", "-1"], SEED_RANGE, id="eval --seed -1"),
    pytest.param(lambda tmp, run: ["video", str(run), "--seed", "-1"], SEED_RANGE, id="video --seed -1"),
    pytest.param(_python_wrong_type, None, id="python total_steps = 'abc'"),
    pytest.param(_python_mistyped_key, None, id="python total_step = 100"),
]


@pytest.mark.parametrize("make, fragment", CASES)
def test_no_traceback_from_user_input(make, fragment, tmp_path, run_dir, capsys):
    """`fragment` None: the command succeeds (exit 0); EITHER: that or one line; else it fails with
    one line containing `fragment`, exit 2."""
    args = make(tmp_path, run_dir)
    if args is None:  # a Python case: it asserted its exception itself
        return
    try:
        code = main(args)
    except SystemExit as e:  # argparse's usage errors
        code = e.code
    err = capsys.readouterr().err.strip()
    if fragment is None or (fragment == EITHER and code == 0):
        assert code == 0, err
        return
    fragment = "" if fragment == EITHER else fragment
    assert code == 2 and len(err.splitlines()) == 1 and err.startswith("relayrl: error:"), err
    assert fragment in err


def test_out_into_a_missing_folder_is_created(tmp_path, run_dir):
    out = relayrl.plot_run(run_dir, tmp_path / "a" / "b" / "r.png")
    assert out.is_file()
    exported = relayrl.export_policy(run_dir, tmp_path / "c" / "p.pt2")
    assert exported.is_file() and (tmp_path / "c" / "p.pt2.json").is_file()


def test_export_line_says_the_input(run_dir, tmp_path, capsys):
    assert main(["export", str(run_dir), "--out", str(tmp_path / "p.pt2")]) == 0
    assert "input obs float32 [batch, 4] -> output action int64 [batch]" in capsys.readouterr().out


def test_export_takes_the_format_from_out(run_dir, tmp_path):
    pytest.importorskip("onnx")
    assert main(["export", str(run_dir), "--out", str(tmp_path / "p.onnx")]) == 0
    assert (tmp_path / "p.onnx").read_bytes()[:1] != b"PK"  # ONNX protobuf, not a torch.export zip


def test_export_refuses_an_out_of_another_extension(run_dir, tmp_path, capsys):
    for name in ("x.txt", "y.PT2"):  # torch.export's reader goes by the extension, case and all
        assert main(["export", str(run_dir), "--out", str(tmp_path / name)]) == 2
        assert "give a file name ending in .pt2 or .onnx, or a folder" in capsys.readouterr().err
    assert main(["export", str(run_dir), "--out", str(tmp_path / "v2.0") + "/"]) == 0  # a folder, dotted name
    assert (tmp_path / "v2.0" / "policy.pt2").is_file()


def test_export_refuses_an_out_that_names_another_format(run_dir, tmp_path, capsys):
    assert main(["export", str(run_dir), "--format", "onnx", "--out", str(tmp_path / "q.pt2")]) == 2
    assert ("--out '" + str(tmp_path / "q.pt2") + "' names the pt2 format but --format is onnx"
            in capsys.readouterr().err)
    assert not (tmp_path / "q.pt2").exists()


def test_onnx_without_the_package_is_one_line(run_dir, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "onnx", None)  # import onnx raises ImportError
    assert main(["export", str(run_dir), "--format", "onnx", "--out", str(tmp_path / "p.onnx")]) == 2
    assert "pip install -e \".[onnx]\" in relayrl's folder" in capsys.readouterr().err


# ---- relayrl config, --version, help -------------------------------------------------------------
@pytest.mark.parametrize("preset", sorted(relayrl.list_presets()))
def test_config_prints_the_full_preset_with_meanings(preset, capsys):
    assert main(["config", preset]) == 0
    text = capsys.readouterr().out
    config = relayrl.load_config(preset)
    assert to_dict(from_dict(tomllib.loads(text))) == to_dict(config)  # the same config, every key
    assert "total_steps = " in text and "# env steps" in text


def test_every_config_field_has_a_meaning():
    config = relayrl.load_config("dqn-cartpole-fast")
    sections = [config, *(getattr(config, f.name) for f in dataclasses.fields(config)
                          if dataclasses.is_dataclass(getattr(config, f.name)))]
    sections += [a.config() for a in relayrl.agents.registry.ALGORITHMS.values()]
    for section in sections:
        about = meanings(type(section))
        for f in dataclasses.fields(section):
            if not dataclasses.is_dataclass(getattr(section, f.name)):
                assert about.get(f.name), f"{type(section).__name__}.{f.name} has no comment saying what it is"
    assert "max_episode_steps = 0  # episode step limit for training and evaluation: a registered id's own is " \
        "replaced (longer or shorter)" in commented_toml(config)


def test_version_and_bare_command(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.strip() == f"relayrl {relayrl.__version__}"
    assert main([]) == 2  # no command ran: the help, exit 2
    assert "usage: relayrl" in capsys.readouterr().out


def test_every_cli_flag_has_help():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.choices and isinstance(a.choices, dict))
    missing = []
    for name, p in [("relayrl", parser), *sub.choices.items()]:
        for action in p._actions:
            if action.help in (None, "") and action.dest not in ("help", "command"):
                missing.append(f"{name} {'/'.join(action.option_strings) or action.dest}")
    assert not missing, missing


def test_bare_relayrl_prints_help_in_a_subprocess(cli_env, tmp_path):
    r = subprocess.run([sys.executable, "-m", "relayrl"], capture_output=True, text=True, env=cli_env, timeout=120)
    assert r.returncode == 2 and "usage: relayrl" in r.stdout and "Traceback" not in r.stderr


def test_did_you_mean_on_the_command_line(capsys):
    assert main(["config", "dqn-cartpole", "--set", "train.total_step=5"]) == 2
    assert capsys.readouterr().err.strip() == (
        "relayrl: error: unknown config key 'train.total_step'; did you mean 'train.total_steps'?")
    assert main(["config", "dqn-cartpol"]) == 2
    assert "did you mean 'dqn-cartpole'?" in capsys.readouterr().err
    with pytest.raises(UserError, match="algo='sca' is not known; did you mean 'sac'"):
        relayrl.load_config("dqn-cartpole", ["algo=sca"])


def test_config_assignment_coerces_and_keeps_valid_values():
    config = relayrl.load_config("dqn-cartpole-fast")
    config.agent.lr = 1  # an int where a float goes, as from TOML
    config.train.total_steps = 5_000
    assert config.agent.lr == 1.0 and isinstance(config.agent.lr, float) and config.train.total_steps == 5_000
    with pytest.raises(ConfigError, match="agent.hidden"):
        config.agent.hidden = "big"
    # a whole section of the wrong kind is refused where it is assigned, not at train()
    with pytest.raises(ConfigError, match=r"^agent=\{'hiden': \[3\]\} has the wrong type; expected the DQNConfig"):
        config.agent = {"hiden": [3]}
    assert type(config.agent).__name__ == "DQNConfig" and config.agent.lr == 1.0


# ---- TensorBoard and progress lines -----------------------------------------------------------
def test_tensorboard_names_as_cleanrl(run_dir):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    tb = EventAccumulator(str(run_dir / "tb"), size_guidance={"scalars": 0, "tensors": 0})
    tb.Reload()
    returns, lengths = tb.Scalars("charts/episodic_return"), tb.Scalars("charts/episodic_length")
    assert len(returns) == len(lengths) > 5  # one point per finished training episode
    # CartPole pays 1 per step: each episode's return is its length, logged at the step it ended
    assert [(e.step, e.value) for e in returns] == [(e.step, e.value) for e in lengths]
    assert all(0 < a.step <= b.step for a, b in zip(returns, returns[1:], strict=False))
    for tag in ("charts/epsilon", "charts/learning_rate", "perf/sps"):
        steps = [e.step for e in tb.Scalars(tag)]
        assert steps == sorted(set(steps)) and steps[-1] == 300, tag  # no duplicate final point
    assert tb.Scalars("perf/sps")[-1].value > 0  # the run's steps/s, not the last instant's 0
    assert tb.Scalars("charts/epsilon")[-1].value < 1.0
    assert "config/text_summary" in tb.Tags()["tensors"]
    # one event file: a second, hparams' own, made W&B's sync_tensorboard read every point twice
    assert [p.name.startswith("events.") for p in (run_dir / "tb").iterdir()] == [True]
    assert _hparams(run_dir) == (["eval/average_return"], True)  # a finished run's session has ended


def _hparams(run_dir):
    """The metrics TensorBoard's HParams dashboard shows for the run, and whether its session ended."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from tensorboard.plugins.hparams.plugin_data_pb2 import HParamsPluginData

    tb = EventAccumulator(str(run_dir / "tb"))
    tb.Reload()
    content = tb.PluginTagToContent("hparams")
    experiment = HParamsPluginData.FromString(content["_hparams_/experiment"]).experiment
    return [m.name.tag for m in experiment.metric_infos], "_hparams_/session_end_info" in content


def test_tensorboard_marks_a_failed_run_unfinished_and_shows_a_resumes_settings(tmp_path):
    """The HParams dashboard called every run a success from its first step (a crashed one too),
    and a resume's changed settings never reached TensorBoard's config text."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    def fail(row):
        if row["step"] >= 400:  # past the checkpoint at 300
            raise ValueError("the user's callback")

    config = relayrl.load_config("dqn-cartpole-fast", [*TINY, "train.total_steps=600", "train.checkpoint_interval=300"])
    with pytest.raises(ValueError):
        relayrl.train(config, tmp_path / "r", progress=False, callbacks=[fail])
    assert _hparams(tmp_path / "r") == (["eval/average_return"], False)
    longer = relayrl.load_config(str(tmp_path / "r" / "config.toml"), ["train.total_steps=900"])
    relayrl.train(longer, tmp_path / "r", resume=True, progress=False)
    assert _hparams(tmp_path / "r")[1]
    tb = EventAccumulator(str(tmp_path / "r" / "tb"), size_guidance={"tensors": 0})
    tb.Reload()
    texts = {e.step: e.tensor_proto.string_val[0].decode() for e in tb.Tensors("config/text_summary")}
    assert "total_steps = 600 " in texts[0] and "total_steps = 900 " in texts[max(texts)] and max(texts) > 0


def test_progress_lines_without_a_terminal(tmp_path, monkeypatch, capsys):
    from relayrl.training.heartbeat import ProgressLines

    monkeypatch.setattr(ProgressLines, "interval_s", 0.02)
    config = relayrl.load_config("dqn-cartpole-fast", [*TINY, "train.total_steps=1500"])
    relayrl.train(config, tmp_path / "r", progress=True)  # pytest's stderr is no TTY: no bar
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("step ") and "/1,500 (" in line]
    assert lines and "env steps/s" in lines[0], err
    # the rate since the line before, and the time left at it (not the run's since its start, warm-up included)
    assert any(re.search(r" env steps/s \| ~\d+ (s|min|h) left \| train return", line) for line in lines), lines
    # the latest training episodes' mean return, once there are some (CartPole's end within 1,500 steps)
    assert re.search(r"\| train return \d+\.\d\d \|", lines[-1]), lines[-1]


def test_the_time_left_reads_in_its_largest_readable_unit():
    from relayrl.training.report import duration

    assert [duration(n, 10.0) for n in (450, 6_000, 1_980_000)] == ["45 s", "10 min", "55.0 h"]
