"""The `relayrl` command: presets | config | train | eval | plot | video | export. Thin: parse, build, call.

`relayrl` with no command prints the help and exits with 2 (no command ran), as argparse does
for a missing argument."""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import re
import signal
import sys
from pathlib import Path
from typing import Any, NoReturn

from relayrl import interrupts
from relayrl.errors import NonFiniteError, UserError
from relayrl.streams import pipe_safe

# export.load_policy's trust_code, for the commands that read a policy file on its own
TRUST_CODE = ("a policy file outside a run directory whose network a user's encoder builds (package.module:make): "
              "import and run that code (a policy file on its own runs none otherwise)")
EXIT_USAGE = 2
EXIT_NON_FINITE = 3  # a run stopped at a NaN or inf; its last good checkpoint and policy are kept


class _Parser(argparse.ArgumentParser):
    """argparse that reports bad usage in one line (no usage dump), exit code 2, naming the
    option meant where an unknown one is close to a known one."""

    options: frozenset[str] = frozenset()  # this command's long options (each parser adds its own)

    def add_argument(self, *args: Any, **kwargs: Any) -> argparse.Action:
        self.options = self.options | {a for a in args if isinstance(a, str) and a.startswith("--")}
        return super().add_argument(*args, **kwargs)

    def unrecognized(self, extra: list[str]) -> NoReturn:
        """Arguments this command does not take, naming the option meant where one is close."""
        import difflib

        message = f"unrecognized arguments: {' '.join(extra)}"
        for i, word in enumerate(extra):
            flag = word.split("=")[0]
            if flag in ("--seed", "--device") and "--set" in self.options:  # `relayrl config`'s: no --seed of its own
                value = word.split("=", 1)[1] if "=" in word else next(iter(extra[i + 1:]), "VALUE")
                message += f"; this command takes it as --set {flag[2:]}={value}"
                break
            near = difflib.get_close_matches(flag, sorted(self.options), n=1, cutoff=0.7)
            if word.startswith("--") and near:
                message += f"; did you mean {near[0]}?"
                break
            if word.startswith("--") and "--set" in self.options and (said := _ported_flag(flag, word, extra[i + 1:])):
                message += f"; {said}"
                break
        self.error(message)

    def error(self, message: str) -> NoReturn:
        print(f"relayrl: error: {message} (see '{self.prog} --help')", file=sys.stderr)  # prog: "relayrl train"
        sys.exit(EXIT_USAGE)


def _split_set(tokens: list[str], extra: list[str]) -> str | None:
    """The line for the first `--set KEY=VALUE` the shell split into words (`KEY VALUE`, `KEY =
    VALUE`, `KEY =VALUE`, `KEY= VALUE`, an unquoted `KEY=[1 2]`), saying the one word meant;
    None where there is none. `extra`: the words argparse left over."""
    for i, word in enumerate(tokens[:-1]):
        if word != "--set":
            continue
        key, rest = tokens[i + 1], tokens[i + 2:]
        nxt = rest[0] if rest else ""
        if "=" not in key and nxt == "=" and len(rest) > 1:
            said, meant = f"{key} = {rest[1]}", f"{key}={rest[1]}"
        elif "=" not in key and nxt.startswith("=") and len(nxt) > 1:
            said, meant = f"{key} {nxt}", f"{key}{nxt}"
        elif "=" not in key and nxt and not nxt.startswith("-"):
            said, meant = f"{key} {nxt}", f"{key}={nxt}"
        elif key.endswith("=") and nxt in extra and not nxt.startswith("-"):  # KEY= alone is an empty value
            said, meant = f"{key} {nxt}", f"{key}{nxt}"
        elif "=" in key and key.split("=", 1)[1].startswith("[") and "]" not in key and nxt in extra:
            parts = [key.split("=", 1)[1]] + list(itertools.takewhile(lambda w: "]" not in w, rest))
            parts += rest[len(parts) - 1:len(parts)]  # the word that closes the list
            items = ", ".join(p.strip("[],") for p in parts if p.strip("[],"))
            return (f"--set {key} {' '.join(parts[1:])}: the shell split the list at its spaces; quote it, with "
                    f"commas between the entries (--set '{key.split('=', 1)[0]}=[{items}]')")
        else:
            continue
        return f"--set {said}: --set takes KEY=VALUE as one word (--set {meant})"
    return None


def _ported_flag(flag: str, word: str, rest: list[str]) -> str | None:
    """Another library's flag (CleanRL's --env-id, --total-timesteps) as relayrl's setting: its
    mapping line and the --set that gives it, where the flag names one."""
    from relayrl.config_fields import fold_key, ported_name

    meaning = ported_name(fold_key(flag[2:]))
    if meaning is None:
        return None
    value = word.split("=", 1)[1] if "=" in word else rest[0] if rest and not rest[0].startswith("-") else "VALUE"
    target = re.match(r"(?:\S+'s \S+ is )([a-z_]+\.[a-z_]+|device|seed)\b", meaning)
    # a flag's true / false (CleanRL's --cuda false) is no value of the key it maps to
    example = f" (--set {target.group(1)}={value})" if target and value not in ("VALUE", "true", "false") else ""
    return f"relayrl takes settings as --set KEY=VALUE{example}: {meaning}"


def _seed(text: str) -> int:
    """--seed's type: an integer in [0, 2**63 - 1], which every consumer of a seed accepts."""
    from relayrl.seeding import seed_problem

    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid int value: {text!r}") from None
    if (problem := seed_problem(value, None)) is not None:
        raise argparse.ArgumentTypeError(problem)
    return value


def build_parser() -> _Parser:
    from relayrl import __version__

    p = _Parser(prog="relayrl", description="Deep RL on PyTorch and Gymnasium.")
    p.add_argument("--version", action="version", version=f"relayrl {__version__}")
    sub = p.add_subparsers(dest="command", parser_class=_Parser)
    p.set_defaults(parsers=sub.choices)  # command -> its parser, for `unrecognized`
    sub.add_parser("presets", help="list preset names with a short description")
    t = sub.add_parser("train", help="train a preset or a config TOML into a run directory")
    t.add_argument("config", metavar="PRESET|CONFIG.toml", nargs="?",
                   help="what to train (with --resume it may be left out: the run's own config.toml is used)")
    t.add_argument("--run-dir", help="where to write the run (default: runs/<algo>-<env>-s<seed>-<time>)")
    t.add_argument("--seed", type=_seed, help="the run's seed; every random stream derives from it (default: 0)")
    t.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config key, e.g. --set train.total_steps=20000 (repeatable)")
    t.add_argument("--resume", action="store_true", help="continue the run in --run-dir from its last checkpoint")
    t.add_argument("--overwrite", action="store_true",
                   help="replace the run already in --run-dir (its checkpoints, metrics and policy are deleted)")
    t.add_argument("--no-progress", action="store_true", help="no progress bar")
    e = sub.add_parser("eval", help="evaluate a run's saved policy; prints one JSON object")
    e.add_argument("run_dir", metavar="RUN_DIR", help="a run directory, or a policy file (policy/policy.pt)")
    e.add_argument("--episodes", type=int, default=10, help="episodes to average over (default: 10)")
    e.add_argument("--seed", type=_seed, default=0,
                   help="seed of the evaluation episodes: copy i is reset with seed + i (default: 0)")
    e.add_argument("--env", metavar="ENV_ID",
                   help="evaluate on this env (a Gymnasium id or package.module:Class) instead of the run's own "
                        "(config.toml's, with its env.kwargs, eval.env_kwargs and wrappers); the id the policy was "
                        "trained on gets the env.kwargs and time limit the policy file records, any id a run "
                        "directory's env.wrappers (a policy file's with --trust-code); for a policy file outside a "
                        "run directory the default is the env id the file records")
    e.add_argument("--max-episode-steps", type=int, default=None, metavar="N",
                   help="cut evaluation episodes at N steps (default: the run's env.max_episode_steps, else the "
                        "env's own time limit, else 1,000)")
    e.add_argument("--trust-code", action="store_true", help=TRUST_CODE)
    e.add_argument("--stochastic", action="store_true",
                   help="sample the SAC or PPO policy's actions (drawn from --seed) instead of taking its mean or "
                        "most likely action; DQN's greedy policy acts the same")
    pl = sub.add_parser("plot", help="PNG of average return against env steps (several runs: compared)")
    pl.add_argument("run_dir", metavar="RUN_DIR", nargs="+",
                    help="a run directory; several, or a folder holding them (a sweep's): their evaluation "
                         "returns in one panel (runs that differ only in their seed: one mean curve with a "
                         "min-to-max band)")
    pl.add_argument("--out", metavar="PNG",
                    help="where to write it (default: RUN_DIR/returns.png, or compare.png beside several runs; "
                         "folders are created)")
    v = sub.add_parser("video", help="a video (MP4, GIF, ...) of the greedy policy")
    v.add_argument("run_dir", metavar="RUN_DIR", help="a run directory")
    # video.VIDEO_SUFFIXES, written out: that module imports torch, which --help does not wait for
    v.add_argument("--out", metavar="MP4|GIF|MKV|MOV|AVI",
                   help="where to write it, the format from its extension: .mp4, .gif, .mkv, .mov or .avi "
                        "(default: RUN_DIR/video.mp4; folders are created)")
    v.add_argument("--episodes", type=int, default=1, help="episodes to record (default: 1)")
    v.add_argument("--seed", type=_seed, default=0, help="seed of the recorded episodes (default: 0)")
    x = sub.add_parser("export", help="write RUN_DIR/policy/policy.pt2, the policy for plain PyTorch (torch.export), "
                                      "or policy.onnx")
    x.add_argument("run_dir", metavar="RUN_DIR", help="a run directory (or its policy/policy.pt)")
    x.add_argument("--out", metavar="FILE", help="where to write it (default: RUN_DIR/policy/policy.FORMAT; "
                                                 "folders are created)")
    x.add_argument("--format", choices=("pt2", "onnx"),
                   help="pt2: a torch.export program | onnx: an ONNX model (the onnx extra); "
                        "default: --out's extension, else pt2")
    x.add_argument("--trust-code", action="store_true", help=TRUST_CODE)
    c = sub.add_parser("config", help="print a preset's (or config TOML's) full config, each key with its meaning")
    c.add_argument("config", metavar="PRESET|CONFIG.toml", help="a preset name (see `relayrl presets`) or a TOML file")
    c.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config key before printing (repeatable)")
    return p


def backslash_note(run_dir: str) -> str | None:
    """A Windows-style --run-dir (`runs\\lab1`, `C:\\Users\\...`) on an OS whose separator is "/":
    there the backslash is part of one folder's name, so the run would not land where it was meant
    to. A note, not a refusal: such a name is legal, only almost never wanted."""
    if os.sep != "/" or "\\" not in run_dir:
        return None
    slashed = run_dir.replace("\\", "/")
    # quoted by hand: repr would double every backslash of the name the user typed
    return (f"relayrl: note: --run-dir '{run_dir}' has a backslash, which on this OS is part of a folder's "
            f"name, not a separator: the run goes into one folder of that name (write '{slashed}' for "
            f"nested folders)")


def _train(args: argparse.Namespace) -> None:
    from relayrl.config import parse_override
    from relayrl.dispatch import RESUME_OR_OVERWRITE, check_resume_matches, default_run_dir, identity_overrides, train
    from relayrl.presets import load_config
    from relayrl.training.resume import IDENTITY_KEYS
    from relayrl.training.run_dir import RunDir

    if args.run_dir is not None and not args.run_dir.strip():  # `--run-dir "$DIR"` with DIR unset
        raise UserError(f"--run-dir {args.run_dir!r} is empty: give a folder (or leave --run-dir out for a new one "
                        "under ./runs)")
    if args.resume:
        if args.overwrite:
            raise UserError(RESUME_OR_OVERWRITE)
        if not args.run_dir:
            raise UserError("--resume needs --run-dir DIR (the run to continue)")
        rd = RunDir(args.run_dir)
        rd.require()
        if args.config:  # it must name the run's own algorithm and env; the run's config.toml is used
            named = identity_overrides(args.overrides)
            # the seed only where one is given: the preset's own (0) is not the run's
            seeded = args.seed is not None or any(parse_override(o)[0] == ["seed"] for o in named)
            check_resume_matches(load_config(args.config, named, args.seed), rd,
                                 identity=IDENTITY_KEYS if seeded else ("algo", "env.id"))
        config = load_config(str(rd.config), args.overrides, args.seed)
    elif not args.config:
        raise UserError("train needs PRESET|CONFIG.toml (see `relayrl presets`), or --run-dir DIR --resume")
    else:
        config = load_config(args.config, args.overrides, args.seed)
    with contextlib.ExitStack() as stack:
        # named here: an interrupt's line names it
        args.run_dir = args.run_dir or str(stack.enter_context(default_run_dir(config)))
        if not args.resume and (note := backslash_note(args.run_dir)):
            print(note, file=sys.stderr, flush=True)
        result = train(config, args.run_dir, resume=args.resume, progress=not args.no_progress,
                       overwrite=args.overwrite)
    from relayrl.training.report import rounded

    final = result.final
    print(f"run directory: {result.run_dir}")
    ret = final.get("average_return")
    print(f"final evaluation: average_return={ret if ret is None else rounded(ret, 4)} "
          f"at step {final.get('step')} ({final.get('wall_time_s')} s)")


def _eval(args: argparse.Namespace) -> None:
    from relayrl.evaluation import named_env, recorded_env
    from relayrl.export import load_policy
    from relayrl.training.evaluate import eval_cap_note, evaluate
    from relayrl.training.run_dir import RunDir, lone_policy_file

    if args.episodes < 1:
        raise UserError(f"--episodes {args.episodes} is not valid; it must be >= 1")
    if args.max_episode_steps is not None and args.max_episode_steps < 1:
        raise UserError(f"--max-episode-steps {args.max_episode_steps} is not valid; it must be >= 1")
    given = Path(args.run_dir)
    if not lone_policy_file(given):  # a policy file on its own names the env it records
        RunDir.of(given).require()
    # a run directory, its config.toml or policy file, or a lone policy file
    policy = load_policy(given, deterministic=not args.stochastic, seed=args.seed, trust_code=args.trust_code)
    if args.env:  # as it is registered, or with the kwargs the policy records for that same id
        env_id, env = args.env, named_env(args.env, policy, args.episodes, args.max_episode_steps or 0,
                                          say=lambda line: print(f"relayrl: {line}", file=sys.stderr),
                                          run_code=args.trust_code or not lone_policy_file(given))
    else:
        env, env_id = recorded_env(given, args.episodes, args.max_episode_steps or 0, info_keys=True, policy=policy)
    try:
        policy.check_fits(env.observation_spec, env.action_spec)
        if args.env and policy.env_id and policy.env_id != args.env and not policy.env_wrappers:  # else said above
            print(f"relayrl: the policy was trained on {policy.env_id}, evaluated here on {args.env}", file=sys.stderr)
        result = evaluate(env, policy, args.episodes, seed=args.seed)
        note = eval_cap_note(env, env_id)
        if note:
            print(f"relayrl: {note}; --max-episode-steps N sets the cut here", file=sys.stderr)
    except NonFiniteError as e:  # an env that returns NaN rewards: what it gave, not a run that stopped
        raise UserError(str(e)) from None
    finally:
        env.close()  # an env's worker processes or windows never outlive a failed evaluation
    # Rewards are float32 in the batched env: its 7 significant digits drop the noise (0.5999999940395355).
    seven_digits = {k: float(f"{v:.7g}") if isinstance(v, float) else v for k, v in result.items()}
    print(json.dumps({**seven_digits, "policy_env_steps": policy.env_steps}))


class Terminated(KeyboardInterrupt):
    """SIGTERM (`kill`, a cluster scheduler's preemption) or SIGHUP (the terminal closed) during
    `train`: the run stops as on Ctrl-C, with a checkpoint, and Ray actors and env worker
    processes are shut down instead of orphaned."""


# The signals `_on_sigterm` acted on: Ray's blocking calls catch a KeyboardInterrupt raised in
# them (a Terminated too) and raise a plain one, so the exception's type alone can lose the signal.
_TERMINATED: set[int] = set()


def _on_sigterm(signum: int, frame: object) -> NoReturn:
    interrupts.heard(signum)
    _TERMINATED.add(signum)
    raise Terminated


def _stop_signals() -> list[int]:
    """SIGTERM, and SIGHUP where it is not ignored (nohup): `train` stops cleanly on each."""
    hangup = [] if interrupts.HANGUP is None or signal.getsignal(interrupts.HANGUP) == signal.SIG_IGN \
        else [interrupts.HANGUP]
    return [signal.SIGTERM, *hangup]


def _completed(rd: Any, args: argparse.Namespace) -> bool:
    """Whether this command's run in `rd` (a RunDir with a checkpoint) has its last checkpoint at
    or past the command's train.total_steps and an evaluation row at that step: a --resume would
    find nothing to do. Not where the command replaces the run (--overwrite)."""
    from relayrl.presets import load_config  # torch-free
    from relayrl.training.run_dir import checkpoint_step, list_checkpoints

    if args.overwrite:
        return False
    try:  # the command's own config: a --resume's --set train.total_steps extends the run
        total = load_config(str(rd.config) if args.resume else args.config, args.overrides, args.seed).train.total_steps
    except (OSError, ValueError, TypeError, UserError):  # a ConfigError is a UserError; TOML's errors ValueErrors
        return False
    at = checkpoint_step(list_checkpoints(rd.checkpoints)[-1])
    rows = rd.read_metrics()
    return at >= total and bool(rows) and rows[-1]["step"] == at and "average_return" in rows[-1]


def _interrupted_line(what: str, args: argparse.Namespace) -> str:
    """For `train`, offer --resume only where there is a checkpoint to resume from."""
    if args.command != "train":
        return f"relayrl: {what}"
    run_dir = args.run_dir
    try:
        from relayrl.training.run_dir import RunDir

        rd = RunDir(run_dir) if run_dir else None
        resumable = rd is not None and rd.has_checkpoint()
        # A signal during torch's first import leaves parts of it loaded, and importing it again raises or
        # crashes the process: the policy file (read with torch) is looked at only once torch is whole.
        whole = "torch" in sys.modules  # an import that failed took it out again
        trained = rd is not None and not resumable and rd.trained_to(read_policy=whole) > 0  # only if needed
    except (ImportError, AttributeError, OSError):  # torch still importing (no run has started), or unreadable
        resumable = trained = False
    if resumable and _completed(rd, args):  # stopped in the run's last moments, after its end was saved
        return f"relayrl: {what} after the run reached its end and evaluated it: it is complete in {run_dir}"
    if resumable:
        return (f"relayrl: {what}; resume with --resume from the last checkpoint: "
                f"relayrl train --run-dir {run_dir} --resume")
    if trained:
        return (f"relayrl: {what} before the first checkpoint: nothing to resume; the policy and metrics so far "
                f"stay in {run_dir} (a new run there needs --overwrite)")
    where = f" in {run_dir}" if run_dir else ""
    return f"relayrl: {what} before the first checkpoint: nothing to resume; a new run{where} starts over"


def main(argv: list[str] | None = None) -> int:
    with pipe_safe():  # `relayrl train ... | head`: a reader gone does not end the run
        return _main(argv)


def _main(argv: list[str] | None) -> int:
    # The current directory is on the import path (`python -m relayrl` puts it first itself): a
    # user's env.id = mypkg.envs:MyEnv (and env.wrappers) resolve from their project folder.
    # Last, not first: a folder there named as a module a library tries (torch's optional z3) is not imported.
    if "" not in sys.path and os.getcwd() not in sys.path:
        sys.path.append(os.getcwd())
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    tokens = sys.argv[1:] if argv is None else argv
    if split := _split_set(tokens, extra):  # argparse took a piece as the preset, or left it over
        print(f"relayrl: error: {split}", file=sys.stderr)
        return EXIT_USAGE
    if extra:
        (args.parsers.get(args.command) or parser).unrecognized(extra)
    if args.command is None:
        parser.print_help()
        return EXIT_USAGE
    try:
        if args.command == "presets":
            from relayrl.presets import list_presets

            for name, desc in list_presets().items():
                print(f"{name}\t{desc}")
        elif args.command == "train":
            _TERMINATED.clear()
            previous = {sig: signal.signal(sig, _on_sigterm) for sig in _stop_signals()}
            try:
                _train(args)
            finally:
                for sig, handler in previous.items():
                    signal.signal(sig, handler)
        elif args.command == "eval":
            _eval(args)
        elif args.command == "plot":
            from relayrl.plot import plot_run

            print(plot_run(args.run_dir[0] if len(args.run_dir) == 1 else args.run_dir, args.out))
        elif args.command == "video":
            from relayrl.video import record_video

            if args.episodes < 1:
                raise UserError(f"--episodes {args.episodes} is not valid; it must be >= 1")
            print(record_video(args.run_dir, args.out, args.episodes, args.seed))
        elif args.command == "export":
            from relayrl.export import describe, export_policy

            path = export_policy(args.run_dir, args.out, args.format, trust_code=args.trust_code)
            sig = json.loads(path.with_name(path.name + ".json").read_text())
            print(f"{path} ({describe(sig)}; signature in {path.name}.json)")
        elif args.command == "config":
            from relayrl.config import config_toml
            from relayrl.presets import load_config

            print(config_toml(load_config(args.config, args.overrides)), end="")
    except UserError as e:
        print(f"relayrl: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except NonFiniteError as e:
        print(f"relayrl: run stopped: {e}", file=sys.stderr)
        return EXIT_NON_FINITE
    except (MemoryError, RuntimeError) as e:  # during a run (its parts were built: dispatch.train says that one)
        from relayrl.dispatch import out_of_memory

        detail = out_of_memory(e)
        if detail is None:
            raise
        print(f"relayrl: error: out of memory ({detail}): lower the run's sizes (train.collect_steps x "
              "env.num_envs for PPO's rollouts, replay.size, the hidden sizes); checkpoints written so far are kept",
              file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt as e:
        # 128 + the signal's number, as shells report it
        hangup = interrupts.HANGUP
        if hangup is not None and hangup in _TERMINATED:
            what, code = "hung up (the terminal closed)", 128 + hangup
        elif isinstance(e, Terminated) or _TERMINATED:
            what, code = "terminated", 143
        else:
            what, code = "interrupted", 130
        print(_interrupted_line(what, args), file=sys.stderr)
        return code
    return 0


if __name__ == "__main__":
    sys.exit(main())
