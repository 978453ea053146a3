"""What every driver (training/local.py, distributed/driver.py) does the same way: hold the
learner and triggers (`RunCore`), and take a run from its first evaluation to its last
checkpoint (`run_to_end`, through the `Driver` methods only). The process's own state is
training/process.py's, the lines a run starts with training/notes.py's."""

from __future__ import annotations

import random
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from relayrl import atomic, interrupts
from relayrl.config import Config, changes, changes_between, dotted, save_toml, to_dict
from relayrl.config_fields import is_user_encoder
from relayrl.core import Agent
from relayrl.envs.resolve import names_python_factory
from relayrl.errors import NonFiniteError, UserError
from relayrl.metrics import EpisodeStats
from relayrl.nn.encoders import CONV_READY
from relayrl.policy_file import env_action_entries, env_entries
from relayrl.schedules import linear_schedule
from relayrl.specs import check_trained_layout, describe, spec_from_state, spec_state
from relayrl.training.checkpoint import list_checkpoints
from relayrl.training.finite import CHECK_LR, DIVERGED, FiniteWatch, non_finite_metrics, non_finite_tensor, stop
from relayrl.training.history import record_process
from relayrl.training.learner import Learner
from relayrl.training.notes import float_frames_note, start_notes
from relayrl.training.replay_setup import collect_only
from relayrl.training.report import Callback, RunReport, log_config, log_finished, plural
from relayrl.training.resume import check_checkpoint_config, saved_config
from relayrl.training.run_dir import RunDir, checkpoint_step
from relayrl.training.triggers import (
    BestPolicy,
    Checkpointer,
    EvalSeeds,
    IntervalTrigger,
    PolicySaver,
    Progress,
    StepsPerSecondLog,
)


@dataclass
class RunResult:
    """What `relayrl.train` returns: `run_dir`, the run directory (plot_run, record_video and
    load_policy take it); `final`, the run's last evaluation row as metrics.jsonl has it (step,
    average_return, average_episode_length, train/..., losses/...; {} where the run logged
    none); `stopped_early`, True where a callback stopped the run before train.total_steps;
    `evaluations` and `best`, every evaluation row and the one with the highest return."""

    run_dir: Path
    final: dict[str, Any]  # the last evaluation row of metrics.jsonl
    stopped_early: bool = False  # a callback returned False before train.total_steps

    @property
    def evaluations(self) -> list[dict[str, Any]]:
        """Every evaluation row of the run's metrics.jsonl, in step order."""
        return RunDir(self.run_dir).read_metrics()

    @property
    def best(self) -> dict[str, Any]:
        """The evaluation row with the highest average_return (the first of equals, as
        policy/best.pt keeps; {} where there is none): a sweep's objective, where the last
        evaluation is one noisy point."""
        rows = [r for r in self.evaluations if r.get("average_return") is not None]
        return max(rows, key=lambda r: r["average_return"]) if rows else {}


def make_learner(config: Config, agent: Agent, table: Any, device: torch.device, variables: Any,
                 whole_rollouts: bool) -> Learner:
    """A rollout queue's learner (`whole_rollouts`) takes one rollout per step, which the agent
    cuts into its minibatches."""
    c = config
    return Learner(agent, table, 1 if whole_rollouts else c.agent.batch_size, device,
                   prioritized=c.replay.sampler == "prioritized", importance_exponent=c.replay.importance_exponent,
                   priority_eps=c.replay.priority_eps, variables=variables)


class RunCore:
    """The parts every driver holds the same way: agent, learner, report, triggers, the finite
    watch and the run's clock; `env_steps()`, `checkpoint_state()` and the evaluation trigger
    are the driver's."""

    def __init__(self, config: Config, rd: RunDir, agent: Agent, learner: Learner, stats: EpisodeStats,
                 finite: FiniteWatch, *, env_steps: Callable[[], int], checkpoint_state: Callable[[], dict[str, Any]],
                 evaluation: IntervalTrigger, show_progress: bool, callbacks: list[Callback] | None = None,
                 postfix: Callable[[], dict[str, str]] = dict,
                 extra_scalars: Callable[[], dict[str, float]] = dict) -> None:
        c = config
        self.config, self.rd, self.agent, self.learner = config, rd, agent, learner
        self.stats, self.finite = stats, finite
        self.env_steps = env_steps
        self.t0, self.wall_offset = time.perf_counter(), 0.0
        self.report = RunReport(c, rd, stats, show_progress=show_progress, callbacks=list(callbacks or []),
                                progress=self.progress, wall_time=self.wall_time, losses=learner.scalar_metrics,
                                schedules=agent.scalars, postfix=postfix, extra_scalars=extra_scalars)
        self.beta_at = linear_schedule(c.replay.importance_exponent, 1.0, c.train.total_steps)
        self.collect_only = collect_only(c)
        self.policy_saver = PolicySaver(c.train.policy_save_interval, agent, rd.policy,
                                        extra={**env_entries(c), **env_action_entries(agent.action_spec)})
        best = PolicySaver(0, agent, rd.policy, extra=self.policy_saver.extra, name="best.pt")
        self.best_policy = BestPolicy(best) if c.eval.keep_best else None
        self.checkpointer = Checkpointer(c.train.checkpoint_interval, checkpoint_state, rd.checkpoints,
                                         keep=c.train.checkpoint_keep, after=self.policy_saver.save)
        self.sps_log = StepsPerSecondLog(c.train.log_interval, report=self.report.log_progress)
        self.evaluation = evaluation
        self.triggers: list[IntervalTrigger] = [evaluation, self.policy_saver, self.checkpointer, self.sps_log]
        self.restored_config: dict[str, Any] = {}  # the config the restored checkpoint was written with

    def say(self, text: str) -> None:
        self.report.say(text)

    def progress(self) -> Progress:
        return Progress(self.env_steps(), self.agent.train_step)

    def wall_time(self) -> float:
        return self.wall_offset + time.perf_counter() - self.t0

    def step_schedules(self, env_steps: int) -> None:
        self.agent.set_progress(env_steps)
        self.learner.importance_exponent = self.beta_at(env_steps)

    def fire_triggers(self) -> None:
        p = self.progress()
        self.report.tick(p.env_steps)
        due = [trigger for trigger in self.triggers if trigger.due(p)]
        if due or self.finite.due():
            self.check_finite(p, weights=self.policy_saver in due or self.checkpointer in due)
        for trigger in due:  # the others would find nothing due
            if gone := self.rd.gone_line():  # each writes into the run directory (an evaluation's callbacks run)
                raise UserError(gone)
            trigger(p)

    def checkpoint_if_due(self) -> None:
        """After a failure that ended collection: the checkpoint due by the env steps the run
        reached, which the loop could not write (a Ray run hears of an actor's steps from its
        answers, and a failed call gives none). One that cannot be written (a non-finite weight,
        a full disk) is a line: the failure stays the run's error."""
        p = self.progress()
        if not self.checkpointer.due(p):
            return
        try:
            self.check_finite(p, weights=True)
            self.checkpointer(p)
        except Exception as e:
            self.say(f"the checkpoint due at env step {p.env_steps:,} was not written: {e}")

    def check_finite(self, p: Progress, weights: bool) -> None:
        """Stop the run (NonFiniteError) at a NaN or inf in what was collected, the latest losses
        or, before a save, the weights: nothing non-finite is ever evaluated or saved."""
        finding = self.finite.check()
        where = f"by env step {p.env_steps:,} (train step {p.train_step:,})"
        if finding is None or self.finite.found_action:  # a diverged update's loss says more than its actions
            loss = non_finite_metrics(self.learner.last_metrics, self.agent.undefined_metrics)
            if loss is not None:
                finding = (f"{loss} {where}: {CHECK_LR} (agent.lr and the like: too high diverges), "
                           "the reward scale and the env's observations")
        if finding is None and weights:
            name = non_finite_tensor(self.agent.state_dict())
            if name is not None:
                finding = f"the agent's {name} held a NaN or inf {where}: {DIVERGED}"
        if finding is not None:
            raise stop(self.with_encoder(finding), self.kept())

    def with_encoder(self, finding: str) -> str:
        """A diverged run's finding, naming the user's encoder among what to check where its
        network is one (its outputs feed every layer after it)."""
        encoder = getattr(self.config.agent, "encoder", "auto")
        if not is_user_encoder(encoder) or CHECK_LR not in finding:
            return finding
        return f"{finding}, and agent.encoder={encoder!r} (its outputs on these observations)"

    def kept(self) -> str:
        """What a stopped run leaves (a non-finite number, a failure): its last checkpoint and policy."""
        ckpts = list_checkpoints(self.rd.checkpoints)
        parts = [f"the last good checkpoint (env step {int(ckpts[-1].stem.split('-')[1]):,})"] if ckpts else []
        saved = self.policy_saver.saved_progress
        if saved is not None:
            parts.append(f"the policy saved at env step {saved.env_steps:,}")
        elif (self.rd.policy / "policy.pt").is_file():
            parts.append("the policy saved before")
        if not parts:
            return f"nothing was saved in {self.rd.root}"
        return f"{' and '.join(parts)} {'are' if len(parts) > 1 else 'is'} kept in {self.rd.root}"

    def checkpoint_common(self, eval_seeds: EvalSeeds) -> dict[str, Any]:
        """What every driver's checkpoint holds."""
        self.report.log_episodes()
        self.report.sync_metrics()
        return {"version": 2, "config": to_dict(self.config), "spaces": self.spaces(),
                "agent": self.agent.state_dict(), "episode_stats": self.stats.state_dict(),
                **eval_seeds.state_dict(), "wall_time_s": self.wall_time(),
                # the global RNGs (a user's env may draw from them) and the latest losses
                "global_rng": {"torch": torch.get_rng_state(), "numpy": np.random.get_state(),
                               "python": random.getstate()},
                "last_metrics": {k: v.detach().cpu() for k, v in self.learner.last_metrics.items()},
                **({"best_policy": self.best_policy.state_dict()} if self.best_policy is not None else {})}

    def spaces(self) -> dict[str, Any]:
        return {"observation": spec_state(self.agent.obs_spec), "action": spec_state(self.agent.action_spec)}

    def restore_common(self, state: dict[str, Any], eval_seeds: EvalSeeds) -> None:
        """Load `checkpoint_common`'s parts (the evaluations' seed indices into `eval_seeds`) but the
        process's state (the driver's to load, once its envs are back)."""
        check_checkpoint_config(self.config, state, self.rd.config)  # dispatch's did where the build could harm
        self.restored_config = state.get("config", {})
        saved = state.get("spaces")  # checkpoints before spaces were recorded: only their frames' layout
        encoder = self.config.agent.encoder
        if saved is None and encoder in CONV_READY:
            check_trained_layout(spec_state(self.agent.obs_spec), any_bounds=encoder != "auto", recorded=False)
        for kind, now in self.spaces().items():
            if saved is not None and spec_state(spec_from_state(saved[kind])) != now:  # both in today's terms
                raise UserError(f"the env's {kind}s are {describe(spec_from_state(now))} but the run was trained on "
                                f"{describe(spec_from_state(saved[kind]))}: resume with the env settings the run "
                                "started with (leave out the --set keys that change env.kwargs or env.wrappers)")
        try:
            self.agent.load_state_dict(state["agent"])
        except (RuntimeError, KeyError, ValueError) as e:  # torch's size-mismatch report runs over lines
            lines = [line.strip() for line in str(e).splitlines() if line.strip()]
            detail = next((line for line in lines if "mismatch" in line or "key" in line.lower()), lines[0] if lines
                          else type(e).__name__)
            agent, then = self.config.agent, self.restored_config.get("agent", {})
            if is_user_encoder(encoder) and all(then.get(k) == getattr(agent, k) for k in agent.NETWORK):
                raise UserError(f"the checkpoint's networks do not fit ({detail[:240]}) though the run's network "
                                f"settings are the same: agent.encoder={encoder!r} now builds other parameters than "
                                "the run's (did its code change since the run?); resume with the code the run was "
                                "trained with") from None
            raise UserError(f"the checkpoint's networks do not fit this config ({detail[:240]}): resume with the "
                            "settings the run started with (leave out the --set keys that change a network or a "
                            "space)") from None
        self.stats.load_state_dict(state["episode_stats"])
        self.wall_offset = float(state["wall_time_s"])
        eval_seeds.load_state_dict(state)
        if self.best_policy is not None:
            self.best_policy.resume(state.get("best_policy"))

    def load_process_state(self, state: dict[str, Any]) -> None:
        rng = state["global_rng"]
        torch.set_rng_state(rng["torch"])
        np.random.set_state(rng["numpy"])
        random.setstate(rng["python"])
        self.learner.last_metrics = dict(state["last_metrics"])

    def resume_at(self, steps: int) -> None:
        kept, torn = self.rd.truncate_metrics(after_step=steps)
        if torn:
            self.say(f"metrics.jsonl held {plural(torn, 'line')} cut short (a crash or a full disk while it was "
                     "written), now left out: the evaluation rows written there are lost")
        if not kept and steps > 0 and self.config.eval.interval > 0:  # a run's rows start at step 0
            self.say(f"metrics.jsonl held no row (deleted or emptied?): the evaluation rows before env step "
                     f"{steps:,} are lost (TensorBoard's tb/ keeps their scalars); the rows go on from here")
        if kept and kept[-1].get("step") == steps:
            self.report.last_eval = kept[-1]  # a finished run resumed again needs no second final eval
        for trigger in self.triggers:
            trigger.start_at(steps)
        self.finite.checked = steps


class Driver(Protocol):
    """What `run_to_end` asks of a driver. `evaluate_now` may leave its evaluation in flight
    (its row is written when it finishes) until `settle_evals`; `close` is called once by
    whoever made the driver, however the run ends (`dispatch.train`)."""

    core: RunCore

    def restore(self) -> None: ...
    def announce(self) -> None: ...
    def evaluate_now(self, p: Progress) -> None: ...
    def iterate(self) -> None: ...
    def settle_evals(self) -> None: ...
    def save_after_failure(self) -> None: ...
    def close(self) -> None: ...


def run_to_end(driver: Driver, resume: bool = False) -> RunResult:
    """The run directory around the driver's `iterate`: the untrained policy's evaluation and
    save, then the final evaluation, policy save and checkpoint. The driver stays open."""
    core = driver.core
    c, report = core.config, core.report
    core.t0 = time.perf_counter()
    training = False
    changed: list[str] = []
    try:
        for note in start_notes(c, core.rd.config, resume):
            core.say(note)
        if resume:
            saved = saved_config(core.rd)  # read first: restoring cuts metrics.jsonl back to the checkpoint
            driver.restore()  # rewrites metrics.jsonl: open the log only afterwards
            left = core.env_steps() < c.train.total_steps
            # also with nothing left: the checkpoint written at the end holds these settings, and a
            # later resume that extends the run goes on with them
            changed = record_resumed_config(core, saved, schedules=left)
            if not left:
                where = "past" if core.env_steps() > c.train.total_steps else "the end of"
                core.say(f"the run is at env step {core.env_steps():,}, {where} train.total_steps="
                         f"{c.train.total_steps:,}: nothing is left to train (raise train.total_steps to go on)")
        if unused := c.unused_keys():  # after a restore, which may refuse the config
            said = ", ".join(f"{k}={v!r}" for k, v in dotted(to_dict(c)).items() if k in unused)
            core.say(f"{said}: no effect with this run's other settings (see `relayrl config` for what each "
                     f"key applies to)")
        record_process(core.rd.history, core.env_steps(), changed)
        report.open(core.env_steps())
        driver.announce()
        if not resume and (flattened := float_frames_note(c, core.agent.obs_spec)):
            core.say(flattened)
        if resume:  # TensorBoard's config is the resumed run's from its step on
            log_config(report.tb, c, core.env_steps())
        if core.env_steps() == 0 and not resume:  # a run a callback stopped at step 0 has evaluated it
            log_config(report.tb, c)
            core.policy_saver.save(Progress(0, 0))  # `relayrl eval` (and a callback at step 0) works from the start
            if c.eval.interval > 0:  # 0: the final evaluation only (an env whose episodes take minutes)
                driver.evaluate_now(Progress(0, 0))  # the untrained policy, before any collection
        training = True  # from here on a failure has stopped a run under way
        if not report.stop_requested:
            driver.iterate()
        stopped = report.stop_requested and core.env_steps() < c.train.total_steps
        # An interrupt in the last iteration still stops the caller (a notebook's loop over seeds,
        # a shell script): the run is saved as at its end, and a resume runs its final evaluation.
        interrupted = report.interrupted
        if stopped and interrupted is None:
            core.say(f"a callback returned False: the run stops at env step {core.env_steps():,}")
        # an interrupt wants no wait, unless the run reached its end with no checkpoint a resume could evaluate from
        at_end_unresumable = not stopped and not c.train.checkpoint_interval
        finish(driver, core.progress(), evaluate=interrupted is None or at_end_unresumable)
        if interrupted is None:  # at its end, or where a callback stopped it
            log_finished(report.tb, core.env_steps())
        if interrupted is not None:  # KeyboardInterrupt, or the SIGTERM handler's stop
            interrupts.redeliver(interrupted, _stopped_at(core))
        return RunResult(core.rd.root, report.last_eval, stopped_early=stopped)
    except KeyboardInterrupt as e:  # Ctrl-C where no stop was requested (the warm-up, an evaluation, a save)
        if not e.args:  # Python's own: say where the run stopped, as a requested stop says it
            e.args = (_stopped_at(core),)
        raise
    except NonFiniteError as e:  # found below the run (the learner): it says what the run keeps
        if e.kept:
            raise
        # the cause, where it was collected: a NaN reward is named, not the TD error it made
        raise stop(core.with_encoder(core.finite.check() or str(e)), core.kept()) from None
    except Exception as e:  # the env's own exception, or a failure: what is kept is said with it
        if gone := core.rd.gone_line():  # whatever failed for it (TensorBoard's next write): nothing is kept
            raise UserError(f"{gone}; the run stopped at env step {core.env_steps():,}") from None
        _own_notes(e)
        # metrics.jsonl's or TensorBoard's write (the atomic files' say it themselves)
        failed = atomic.unwritable(e, core.rd.root)
        if not training:
            if failed is not None:
                raise UserError(atomic.unwritable_line(failed, core.rd.root)) from None
            raise
        stopped_at = f"the run stopped at env step {core.env_steps():,}"
        if failed is not None:
            raise UserError(f"{atomic.unwritable_line(failed, core.rd.root)}; {stopped_at}: {crash_kept(core)}"
                            ) from None
        driver.save_after_failure()
        # A UserError is one line, said by whoever catches it: the same line says what is kept
        # (where its message is its args; a class of its own making gets a note instead).
        if isinstance(e, UserError) and type(e).__str__ is BaseException.__str__:
            e.args = (f"{e}; {stopped_at}: {crash_kept(core)}",)
        else:  # the user's own traceback (an env's exception) ends with it
            e.add_note(f"relayrl: {stopped_at} on the error above; {crash_kept(core)}")
        raise
    finally:
        report.close(failing=sys.exc_info()[0] is not None)


def _own_notes(e: BaseException) -> None:
    """Ray's exception for a remote one (a RayTaskError that is also the cause's class) reads its
    notes through the cause (its __getattr__), while its message already holds the remote
    traceback that ends with them (the env copy and the rollout actor's env steps): a list of its
    own, so each is said once and the run's note is its own."""
    ray_errors = sys.modules.get("ray.exceptions")
    if ray_errors is not None and isinstance(e, ray_errors.RayTaskError) and "__notes__" not in vars(e):
        e.__notes__ = []


def crash_kept(core: RunCore) -> str:
    """What a run that an exception stopped leaves, and how it goes on once the cause is fixed."""
    if not list_checkpoints(core.rd.checkpoints):
        return (f"{core.kept()}; no checkpoint to resume from: a new run there starts over (with --overwrite, "
                "overwrite=True in Python, where this one trained past env step 0)")
    resume = _python_resume(core)
    if not names_python_factory(core.config.env.id):  # only Python can pass the factory again
        resume = f"`relayrl train --run-dir {core.rd.root} --resume` (in Python: {resume})"
    return f"{core.kept()}: once the cause is fixed, {resume} continues it"


def _python_resume(core: RunCore) -> str:
    factory = ", env=<the same env factory>" if names_python_factory(core.config.env.id) else ""
    return f"relayrl.train(None, {str(core.rd.root)!r}, resume=True{factory})"


def _stopped_at(core: RunCore) -> str:
    """Where an interrupted run stopped and how it goes on, in Python's terms (the CLI says its own)."""
    root, step = str(core.rd.root), core.env_steps()
    if ckpts := list_checkpoints(core.rd.checkpoints):
        at = checkpoint_step(ckpts[-1])
        if step >= core.config.train.total_steps and at >= step:  # Ctrl-C in the last iteration or final save
            if core.report.last_eval.get("step") == step:
                return f"the run reached its last env step ({step:,}) and evaluated it: it is complete in {root!r}"
            return (f"the run reached its last env step ({step:,}) with a checkpoint in {root!r}: "
                    f"{_python_resume(core)} does what was left (its final evaluation)")
        # a second Ctrl-C (or a callback's KeyboardInterrupt) stops between checkpoints: say which one resumes
        since = "" if at == step else f" (env step {at:,}; the steps after it are trained again)"
        return (f"the run stopped at env step {step:,} with a checkpoint{since} in {root!r}: "
                f"{_python_resume(core)} continues it")
    if core.config.train.checkpoint_interval > 0:
        # as a new run there decides (dispatch's takeover): by the steps its files record
        reached = core.rd.trained_to()
        again = ("starts over in it" if reached == 0 else
                 f"needs overwrite=True (its policy and metrics to env step {reached:,} are kept there)")
        return (f"the run stopped at env step {step:,}, before its first checkpoint: nothing to resume; a new run "
                f"in {root!r} {again}")
    return (f"the run stopped at env step {step:,}; its policy and metrics are in {root!r} "
            "(train.checkpoint_interval = 0: no checkpoint to resume from)")


def record_resumed_config(core: RunCore, saved: Config | None, schedules: bool = True) -> list[str]:
    """config.toml becomes the config the resumed run goes on with (`--set` overrides
    included), so that `relayrl eval` and a later resume use it; written once the checkpoint
    has been restored, so a config it refused is not kept. What changed is said, and
    (`schedules`: steps are left to train) which schedules follow a changed total. Returns what
    changed."""
    changed = changes(saved, core.config) if saved is not None else ["config.toml rewritten in this version's form"]
    if saved is not None and (edited := changes_between(core.restored_config, to_dict(saved), fields_in_both=True)):
        core.say(f"config.toml differs from the settings its checkpoint was written with (edited by hand, or a "
                 f"resume stopped before its first checkpoint): {'; '.join(edited)}")
    if changed:
        save_toml(core.config, core.rd.config)
        core.say(f"resumed with changed settings, now in config.toml: {'; '.join(changed)}")
    total = core.config.train.total_steps
    stretched = core.config.agent.over_total_steps()
    if core.config.replay.sampler == "prioritized":  # its importance exponent anneals to 1 at the total
        stretched.append("replay.importance_exponent's annealing")
    # the total the checkpoint's schedules ran to (config.toml's may have been edited by hand)
    before = core.restored_config.get("train", {}).get("total_steps", saved.train.total_steps if saved else total)
    if schedules and before != total and stretched:
        core.say(f"the schedules over train.total_steps ({', '.join(stretched)}) now run to env step {total:,}: "
                 f"from env step {core.env_steps():,} on they follow the new length (a learning rate or epsilon "
                 "that had decayed rises again where the run is extended)")
    return changed


def finish(driver: Driver, p: Progress, evaluate: bool = True) -> None:
    """The final evaluation (unless one ran at this step, or not `evaluate`), policy save,
    checkpoint and log. Without `evaluate` (an interrupt), the evaluation of an interval
    boundary passed since the last one still runs: a Ray run's count can cross one after its
    loop ended (steps its halted actors had shipped), and a resume starts past it."""
    core = driver.core
    core.check_finite(p, weights=True)
    evaluated = (evaluate or core.evaluation.due(p)) and core.report.last_eval.get("step") != p.env_steps
    try:
        if evaluated:
            driver.evaluate_now(p)
        driver.settle_evals()
    except KeyboardInterrupt:  # Ctrl-C in the final evaluation (the only one with eval.interval = 0):
        _save(core, p, changed=True)  # the run is kept without it; a resume evaluates it
        raise
    _save(core, p, changed=evaluated)
    if core.report.scalars_step != p.env_steps:  # a stop on a log row's step: its scalars are there once
        core.report.write_scalars(p, *core.report.run_sps(p))


def _save(core: RunCore, p: Progress, changed: bool) -> None:
    """The policy and a checkpoint at `p`. A checkpoint the loop wrote at `p` is written again
    only where the run `changed` since (its final evaluation's count): with a large replay
    the write takes a while and as much disk again."""
    if gone := core.rd.gone_line():  # the saves would recreate its folders
        raise UserError(gone)
    core.policy_saver.save(p)
    if core.config.train.checkpoint_interval > 0 and (changed or core.checkpointer.saved_progress != p):
        core.checkpointer.save(p)
