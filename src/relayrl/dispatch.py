"""`train()`: the drivers' dispatch, at the top of the package so that nothing below imports
upward. One driver per topology: the one-process Actor + Learner (training/local.py), the same
on Ray with distributed.num_actors > 0 (distributed/driver.py, and distributed/onpolicy.py for
a rollout queue), or, for an algorithm that trains by itself, training/direct.py."""

from __future__ import annotations

import contextlib
import copy
import functools
import inspect
import itertools
import os
import re
import threading
import time
import types
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import gymnasium as gym

from relayrl import console
from relayrl.agents.registry import ALGORITHMS, Algorithm, algorithm, ray_algorithms
from relayrl.config import Config, algo_defaults, dotted, from_dict, load_toml, parse_override, save_toml, to_dict
from relayrl.envs.resolve import names_python_factory
from relayrl.errors import CheckpointError, ConfigError, UserError, one_line
from relayrl.presets import load_config
from relayrl.training.direct import DirectDriver
from relayrl.training.lifecycle import RunResult
from relayrl.training.local import LocalDriver
from relayrl.training.process import caller_state_kept
from relayrl.training.report import Callback
from relayrl.training.resume import IDENTITY, check_checkpoint_config, kept_on_resume
from relayrl.training.run_dir import RunDir

if TYPE_CHECKING:
    from relayrl.distributed.driver import RayDriver


_NAMED: set[Path] = set()  # the folders `default_run_dir` named, which a run says it writes to


@contextlib.contextmanager
def default_run_dir(config: Config) -> Iterator[Path]:
    """runs/<algo>-<env>-s<seed>-<date>-<time>, with -2, -3, ... where runs started within the same
    second (a sweep of short runs) would share it. The name is claimed by making the folder, so
    runs started at once in several processes each get their own; an empty folder is taken out
    again when the block ends (bad input found before the run wrote anything)."""
    name = config.env.id.replace("/", "_").replace(":", "_").replace("<", "").replace(">", "")
    base = Path("runs") / f"{config.algo}-{name}-s{config.seed}-{time.strftime('%Y%m%d-%H%M%S')}"
    made_runs = not base.parent.exists()
    for path in itertools.chain([base], (base.with_name(f"{base.name}-{i}") for i in itertools.count(2))):
        try:
            path.mkdir(parents=True)
            break
        except FileExistsError:
            continue
        except OSError:  # not writable here: the run's own check says so in one line
            break
    _NAMED.add(path)
    try:
        yield path
    finally:
        _NAMED.discard(path)
        for made in (path, base.parent) if made_runs else (path,):
            with contextlib.suppress(OSError):  # only an empty folder goes
                made.rmdir()


def factory_env_id(factory: Callable[[], Any]) -> str:
    """The env.id a factory given in Python is recorded as: `module:name` for a module-level
    function or class, which a later `relayrl eval` or resume can import; `module:<...>` for
    anything else, which no import finds, so those commands ask for the same env=."""
    if isinstance(factory, functools.partial):  # a sweep over an env's arguments: each run's are its own
        # an object's repr names its address, another in every process: left out
        given = [re.sub(r" at 0x[0-9a-fA-F]+", "", text) for text in
                 [repr(a) for a in factory.args] + [f"{k}={v!r}" for k, v in factory.keywords.items()]]
        module, _, func = factory_env_id(factory.func).partition(":")
        return f"{module}:<partial({one_line(', '.join([func.strip('<>'), *given]), 200)})>"
    module = getattr(factory, "__module__", None) or type(factory).__module__
    name: str | None = getattr(factory, "__qualname__", None)
    if isinstance(factory, (types.FunctionType, type)) and name is not None and name.isidentifier():
        return f"{module}:{name}"
    label = name if name and "<" in name else f"<{name or type(factory).__qualname__}>"
    return f"{module}:{label}"


RESUME_OR_OVERWRITE = "--overwrite replaces a run, --resume continues it: pass one of them"

def identity_overrides(overrides: Sequence[str]) -> list[str]:
    """The `--set` overrides that touch a key of `IDENTITY` (or a section holding one): what a
    preset named on a resume is checked with. The others change the run's own config.toml, and
    checked against the preset's settings instead they could refuse what the run allows."""
    def touches(keys: list[str]) -> bool:
        return any(name.split(".")[:len(keys)] == keys for name in IDENTITY)
    return [text for text in overrides if touches(parse_override(text)[0])]


def check_resume_matches(config: Config, rd: RunDir, identity: Sequence[str] | None = None) -> None:
    """A resumed run is the run in `rd`: a config that changes one of the keys it keeps
    (`resume.kept_on_resume`; with `identity`, those of algo, env.id and seed it names) is one line."""
    saved = dotted(load_toml(rd.config))
    defaults, now = dotted(to_dict(algo_defaults(saved.get("algo", config.algo)))), dotted(to_dict(config))
    replay = saved.get("train.checkpoint_replay", defaults["train.checkpoint_replay"])
    checked = kept_on_resume(config, replay) if identity is None else {k: IDENTITY[k] for k in identity}
    for key, advice in checked.items():
        if now[key] != (was := saved.get(key, defaults[key])):
            raise UserError(f"--resume: {key}={now[key]!r} but the run in {str(rd.root)!r} has {was!r}; {advice}")


def _check_memmap_checkpoint(config: Config, rd: RunDir) -> None:
    """A memmap replay's files are laid out again when the run is built with another layout:
    the checkpoint's own config is checked first (a RAM replay's run checks it on restore,
    without reading a large checkpoint twice)."""
    if config.replay.storage != "memmap" or not rd.has_checkpoint():
        return
    from relayrl.training.checkpoint import load_latest_checkpoint

    with contextlib.suppress(CheckpointError):  # none readable: the restore says so
        check_checkpoint_config(config, load_latest_checkpoint(rd.checkpoints), rd.config)


def _use_factory(config: Config, env: Any, one_process: bool) -> None:
    """Check an env factory given to `train` and record it as the config's env.id."""
    if isinstance(env, gym.Env):  # SB3's habit: one instance, which cannot be the run's several copies
        registered = env.spec.id if env.spec is not None else None
        way = (f"set env.id={registered!r} (and env.kwargs)" if registered else
               f"give a callable returning one (env=lambda: {type(env.unwrapped).__name__}(...)), or name it in env.id")
        raise UserError(f"env={env!r} is an env instance: relayrl makes its own copies to train and evaluate on; "
                        + way)
    if isinstance(env, gym.vector.VectorEnv):  # SB3's make_vec_env habit
        raise UserError(f"env={type(env).__name__} is a vector env: relayrl makes and batches its own copies; "
                        "give a callable returning one env, and set env.num_envs (env.vectorization = async for "
                        "worker processes)")
    if isinstance(env, str):
        raise UserError(f"env={env!r} is an env id: set it as the config's env.id (config.env.id = {env!r}, or "
                        f"--set env.id={env}); env= takes a callable returning an env")
    if not callable(env):
        raise UserError(f"env={env!r} is not a callable returning a Gymnasium env (e.g. lambda: MyEnv())")
    if not one_process and config.distributed.num_actors > 0:
        raise UserError("env=<factory> works with the one-process Actor + Learner run; name the env in "
                        "env.id as package.module:make_env instead")
    if not one_process:  # an algorithm that trains by itself, through its own envs
        learners = ", ".join(name for name, entry in ALGORITHMS.items() if entry.replay != "none")
        raise UserError(f"env=<factory> works with the Actor + Learner runs ({learners}); algo={config.algo!r} "
                        "trains through its own env (env.id)")
    config.env.id = factory_env_id(env)


def _check_callbacks(callbacks: Sequence[Callback] | None, actor_learner: bool) -> list[Callback]:
    callbacks = [callbacks] if callable(callbacks) else list(callbacks or [])  # callbacks=cb: a list of one
    for cb in callbacks:
        if not callable(cb):
            raise UserError(f"callbacks: {cb!r} is not callable; give functions taking a metrics row (a dict)")
        if not _takes_one_argument(cb):  # else a TypeError from the step-0 evaluation, the run half made
            raise UserError(f"callbacks: {getattr(cb, '__qualname__', cb)!r} cannot be called with one argument; a "
                            "callback takes the metrics row (a dict) alone: def cb(row) (SB3's callback objects "
                            "and (locals, globals) functions are not taken)")
    if callbacks and not actor_learner:
        raise UserError("callbacks= works with the Actor + Learner runs (algo dqn, sac or ppo, in one process or "
                        "on Ray); this algorithm trains by its own loop")
    return callbacks


def _takes_one_argument(fn: Callable[..., Any]) -> bool:
    """Whether `fn(row)` binds; True where Python cannot tell (a builtin without a signature)."""
    try:
        signature = inspect.signature(fn)
    except (TypeError, ValueError):
        return True
    try:
        signature.bind(None)
    except TypeError:
        return False
    return True


_REPLACE = "pass --overwrite to replace it, or choose another --run-dir (in Python: overwrite=True, or another run_dir)"


def _keep_recorded_factory(config: Config, rd: RunDir) -> None:
    """A resume given a functools.partial env factory of a run an earlier version recorded as
    `functools:<partial>` (without its arguments) keeps that env.id, so the resume is not refused
    as another env's."""
    with contextlib.suppress(ConfigError, OSError):
        recorded = str(load_toml(rd.config).get("env", {}).get("id", ""))
        if recorded == "functools:<partial>" and ":<partial(" in config.env.id:
            config.env.id = recorded


def _takeover_notice(rd: RunDir, overwrite: bool) -> str | None:
    """The notice of a new run that replaces the run in `rd` (None: no run there), or a UserError
    where that run is worth keeping (a checkpoint, finished, trained past step 0)."""
    if not (rd.metrics.exists() or rd.config.exists()):
        if overwrite and rd.root.is_dir() and any(rd.root.iterdir()):
            raise UserError(f"--overwrite: {str(rd.root)!r} is not a relayrl run directory (no config.toml); "
                            "refusing to delete it")
        return None
    if overwrite:
        return f"--overwrite: replacing the run in {str(rd.root)!r}"
    if not rd.has_checkpoint() and not _finished(rd):
        reached = rd.trained_to()
        if reached == 0:  # nothing learned to lose
            return (f"run directory {str(rd.root)!r} holds a run that stopped before its first checkpoint: "
                    "starting over in it")
        raise UserError(f"run directory {str(rd.root)!r} holds a run that stopped at env step {reached:,}, "
                        f"before its first checkpoint (its policy and metrics so far are there); {_REPLACE}")
    if not rd.has_checkpoint():  # finished without checkpoints (bptt's runs write none): nothing to resume
        raise UserError(f"run directory {str(rd.root)!r} already holds a run (finished, with no checkpoint to resume "
                        f"from); {_REPLACE}")
    raise UserError(f"run directory {str(rd.root)!r} already holds a run; pass --resume to continue it, "
                    "--overwrite to replace it, or choose another --run-dir (in Python: relayrl.train(..., "
                    "resume=True) or overwrite=True, or another run_dir)")


def _finished(rd: RunDir) -> bool:
    try:
        saved = from_dict(load_toml(rd.config))
    except Exception:  # a config.toml this version cannot read: keep the run, as if finished
        return True
    if not algorithm(saved.algo).resumable:  # its policy file is written when it ends
        return (rd.policy / "policy.pt").exists()
    rows = rd.read_metrics()
    return bool(rows) and rows[-1].get("step", 0) >= saved.train.total_steps


def train(config: Config | dict[str, Any] | str | Path | None, run_dir: str | Path | None = None, resume: bool = False,
          progress: bool = True, env: Callable[[], Any] | None = None, overwrite: bool = False,
          callbacks: Sequence[Callback] | None = None, quiet: bool = False) -> RunResult:
    """Train from a Config (or a nested dict of config values, a preset's name or a config
    TOML's path, as `load_config` takes them) into a run directory; returns a `RunResult`
    (`.run_dir`, `.final`: the last evaluation's metrics row, `.stopped_early`).

    A new run refuses a directory that already holds a run with a checkpoint (or a finished
    one, or one that trained past step 0), unless `overwrite=True` replaces it; a run that
    stopped before training is taken over. `resume=True` continues the run in `run_dir` from
    its latest checkpoint; the config must name the run's algorithm and env, and `config=None`
    takes the run's own config.toml (as `relayrl train --run-dir DIR --resume`; to change a setting,
    `load_config(DIR / "config.toml", ["train.total_steps=..."])`).

    `env`: a callable returning a Gymnasium env, used instead of `config.env.id` (which is set
    to the callable's `module:name`). Each copy of the env is one call; with
    env.vectorization = "async" the callable is pickled with cloudpickle into the worker
    processes, so it must not hold what cannot be pickled (open files, simulator handles) --
    make those inside it. A resumed run needs the same callable passed again. Distributed runs
    need an importable env.id instead.

    `callbacks`: callables each given a metrics row (a dict) at every evaluation (the row
    metrics.jsonl gets, with `"event": "eval"`) and every train.log_interval env steps
    (`"event": "log"`: step, train_step, wall_time_s, perf/*, train/*, losses/*, charts/*).
    One returning False stops the run cleanly: the final policy and checkpoint are saved and
    the result's `stopped_early` is True. Early stopping at a return of 400:
    `callbacks=[lambda row: row.get("average_return", -1e9) < 400]`. What a callback raises
    propagates; the run's checkpoints so far stay. Actor + Learner runs (dqn, sac, ppo), in one
    process or on Ray.

    `run_dir=None` makes a new one under ./runs named for the algorithm, env, seed and start
    time (`runs/dqn-CartPole-v1-s0-20261129-101500`; `result.run_dir` says which).

    `progress=False` turns the progress bar off; the run's lines (evaluations, notes) still go
    to stderr. `quiet=True` keeps them all back too (a sweep's trials; what goes wrong is still
    raised), in this thread only: other threads' output, Optuna's with n_jobs > 1, stays.
    """
    # The config is checked first: a sweep's bad trial fails at once, not after another thread's run.
    # One run at a time from the run directory's checks on: another thread's run may be writing it.
    with console.quiet(bool(quiet)):
        checked, taken = _checked_config(config, run_dir, resume, env, callbacks)
        with _one_run_at_a_time():
            return _train(checked, run_dir, resume, progress and not quiet, env, overwrite, taken)


def _checked_config(config: Config | dict[str, Any] | str | Path | None, run_dir: str | Path | None, resume: bool,
                    env: Callable[[], Any] | None,
                    callbacks: Sequence[Callback] | None) -> tuple[Config, list[Callback]]:
    """The run's config (a copy, checked, an env factory recorded in it) and its callbacks, checked."""
    if run_dir is not None and (not isinstance(run_dir, str | os.PathLike) or not str(run_dir).strip()):
        raise UserError(f"run_dir={run_dir!r} is not a folder's path: give a str or a Path (None: a new folder "
                        "under ./runs)")
    if config is None:
        if not resume or run_dir is None:
            raise UserError("config=None continues a run with its own config.toml: give run_dir and resume=True "
                            "(a new run needs a config: a preset's name, a config TOML's path, a dict or a Config)")
        own = RunDir(run_dir)
        own.require()
        config = load_config(str(own.config))
    elif isinstance(config, str | Path):
        config = load_config(str(config))
    elif not isinstance(config, Config | dict):
        raise UserError(f"config={config!r} is not a config: give a Config (relayrl.load_config), a dict of "
                        "config values, a preset's name or a config TOML's path")
    # A copy: recording an env factory's name (and the run's own settings) never changes the caller's config.
    config = from_dict(config) if isinstance(config, dict) else copy.deepcopy(config)
    config.validate()
    if config.replay.path:  # recorded absolute: a resume started from another folder finds the files
        config.replay.path = str(Path(config.replay.path).resolve())
    entry = algorithm(config.algo)
    one_process = entry.replay != "none" and config.distributed.num_actors == 0
    if env is not None:
        _use_factory(config, env, one_process)
    callbacks = _check_callbacks(callbacks, entry.replay != "none")
    if config.distributed.num_actors > 0 and names_python_factory(config.env.id):
        raise UserError(f"env.id={config.env.id!r} names an env made in the script itself (a lambda, a local "
                        "function or __main__), which Ray's workers cannot import: put it in a module beside the "
                        "script and name it in env.id as module:name")
    return config, callbacks


def _train(config: Config, run_dir: str | Path | None, resume: bool, progress: bool, env: Callable[[], Any] | None,
           overwrite: bool, callbacks: list[Callback]) -> RunResult:
    entry = algorithm(config.algo)
    with contextlib.ExitStack() as stack:  # a folder of default_run_dir's goes again where the run wrote nothing
        rd = RunDir(run_dir if run_dir is not None else stack.enter_context(default_run_dir(config)))
        rd.check_writable()
        rd.check_not_running()
        if resume:
            if overwrite:
                raise UserError(RESUME_OR_OVERWRITE + " (in Python: overwrite=True or resume=True)")
            rd.require()
            if env is not None:
                _keep_recorded_factory(config, rd)
            check_resume_matches(config, rd)
            _check_memmap_checkpoint(config, rd)
        takeover = None if resume else _takeover_notice(rd, overwrite)
        # files that are not a run's (looked at before the run's parts make a memmap replay's folder)
        beside = not resume and not takeover and rd.root.is_dir() and any(rd.root.iterdir())
        if resume and not entry.resumable:
            raise UserError(f"algo={entry.name!r} runs are not checkpointed (they take minutes): start a new run "
                            "instead")
        if config.distributed.num_actors > 0 and not entry.ray:
            raise UserError(f"algo={entry.name!r} runs in one process only; distributed.num_actors works with "
                            f"{', '.join(ray_algorithms())}")
        with caller_state_kept():  # the run's threads, flushing and seeds are the run's alone
            return _build_and_train(entry, config, rd, resume, progress, env, callbacks, takeover, beside)


# A run seeds torch's global generator (network initialisation) and sets the process's thread
# count and denormal flushing, then puts back the caller's: two runs at once in threads of one
# process (Optuna's n_jobs > 1) drew each other's numbers, and a fixed seed gave another run.
# Reentrant: a callback may start a run of its own.
_RUNNING = threading.RLock()


@contextlib.contextmanager
def _one_run_at_a_time() -> Iterator[None]:
    """Runs started in several threads take turns; a run that waits says why, once."""
    if not _RUNNING.acquire(blocking=False):
        console.say("relayrl: another relayrl.train is running in this process: this one starts when it ends "
                    "(a run sets torch's global generator and thread count; run trials in processes to run them "
                    "side by side)")
        _RUNNING.acquire()
    try:
        yield
    finally:
        _RUNNING.release()


def _build_and_train(entry: Algorithm, config: Config, rd: RunDir, resume: bool, progress: bool,
                     env: Callable[[], Any] | None, callbacks: list[Callback], takeover: str | None,
                     beside: bool) -> RunResult:
    """The run's parts (bad input fails before anything is written), then the run into `rd`."""
    try:
        driver = _make_driver(entry, config, rd, progress, env, callbacks)
    except (MemoryError, RuntimeError, ValueError) as e:
        detail = out_of_memory(e)
        if detail is None:
            raise
        data = (f"replay.size={config.replay.size:,}" if entry.replay == "transitions"
                else f"train.collect_steps={config.train.collect_steps:,}")
        envs = f", env.num_envs={config.env.num_envs:,}" if config.env.num_envs > 1 else ""
        memmap = ", or keep the replay in files (replay.storage=memmap)" if entry.replay == "transitions" else ""
        raise UserError(f"not enough memory to build the run ({detail}): lower {data}{envs} or the networks' sizes "
                        f"(the agent's hidden sizes){memmap}") from None
    result: RunResult | None = None
    try:
        if takeover:
            console.say(f"relayrl: {takeover}")
            rd.clear()
        elif beside:
            console.say(f"relayrl: run directory {str(rd.root)!r} holds other files: the run is written beside them")
        rd.create()
        if rd.root in _NAMED:  # a folder the run named itself: where it goes, now (the command's last line too)
            console.say(f"relayrl: the run is written to {str(rd.root)!r}")
        rd.hold_lock()
        try:
            if not resume:
                save_toml(config, rd.config)
            result = driver.train(resume=resume)
            return result
        finally:
            rd.release_lock()
    finally:
        _close(driver, result is not None)


def _close(driver: Any, finished: bool) -> None:
    """The driver's envs and Ray actors closed: they end with the run, or before it where it never
    started. An env whose own close() raises after the run finished does not turn a finished run,
    whose files are all written, into a failure: one line says so."""
    try:
        driver.close()
    except Exception as e:
        if not finished:
            raise
        console.say(f"relayrl: the run finished and its files are written; then closing its envs raised "
                    f"{type(e).__name__}: {e}")


def out_of_memory(e: BaseException) -> str | None:
    """The allocator's last line where `e` is running out of memory (NumPy's and Python's
    MemoryError, torch's CPU / CUDA allocator refusing); None for any other error."""
    text = str(e).strip()
    # NumPy's "array is too big": more bytes than an address space holds
    if not isinstance(e, MemoryError) and not any(s in text for s in ("can't allocate memory", "not enough memory",
                                                                      "out of memory", "array is too big")):
        return None
    return text.splitlines()[-1][:200] if text else type(e).__name__


def _make_driver(entry: Algorithm, config: Config, rd: RunDir, progress: bool, env: Callable[[], Any] | None,
                 callbacks: list[Callback]) -> LocalDriver | DirectDriver | RayDriver:
    if entry.replay == "none":
        return DirectDriver(config, rd)  # no progress bar: its lines are its evaluations
    if config.distributed.num_actors > 0:
        from relayrl.distributed.driver import RayDriver

        return RayDriver(config, rd, progress, callbacks=callbacks)
    return LocalDriver(config, rd, progress, env_factory=env, callbacks=callbacks)
