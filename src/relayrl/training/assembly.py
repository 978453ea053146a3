"""The one run assembly: the parts every Actor + Learner run is built from, in one process or on Ray.

`Run.__init__` seeds the process, picks the device, asks the subclass for the env specs
(`open`), builds the agent the registry names, asks the subclass for the replay and the
variable container (`connect`), and builds the learner and the triggers (evaluation, policy
save, checkpoint, steps/s log). `Run.run` writes the run directory around the subclass's
`iterate`: the untrained policy's evaluation and save, then the final evaluation, policy save
and checkpoint. A subclass says how it steps envs and evaluates; nothing else differs.
"""

from __future__ import annotations

import random
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from relayrl.agents.registry import algorithm
from relayrl.config import Config
from relayrl.envs.make import check_env, is_user_env
from relayrl.errors import NonFiniteError, UserError
from relayrl.metrics import EpisodeStats
from relayrl.schedules import linear_schedule
from relayrl.seeding import RunSeeds
from relayrl.specs import Spec
from relayrl.training.checkpoint import list_checkpoints
from relayrl.training.finite import FiniteWatch, non_finite_metrics, non_finite_tensor, stop
from relayrl.training.heartbeat import ProgressLines
from relayrl.training.learner import Learner
from relayrl.training.replay_setup import collect_only
from relayrl.training.run_dir import MetricsLog, RunDir
from relayrl.training.triggers import Checkpointer, IntervalTrigger, PolicySaver, Progress, StepsPerSecondLog


@dataclass
class RunResult:
    run_dir: Path
    final: dict[str, Any]  # the last evaluation row of metrics.jsonl
    stopped_early: bool = False  # a callback returned False before train.total_steps


# relayrl.train(callbacks=[...]): each is called with a metrics row (the `event` key says which:
# "eval", the row metrics.jsonl gets at an evaluation, or "log", every train.log_interval env
# steps); returning False stops the run as if it had reached train.total_steps.
Callback = Callable[[dict[str, Any]], Any]


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise UserError(f"device={name!r} but CUDA is not available here; valid: cpu, auto")
    return torch.device(name)


def log_config(tb: Any, config: Config) -> None:
    """The run's config in TensorBoard: as TOML text (with each key's meaning) and as hparams."""
    from relayrl.config import to_dict
    from relayrl.config_fields import commented_toml

    text = commented_toml(config)
    tb.add_text("config", "\n".join("    " + line for line in text.splitlines()))  # a markdown code block
    flat: dict[str, Any] = {}

    def walk(d: dict[str, Any], prefix: str) -> None:
        for k, v in d.items():
            if isinstance(v, dict):
                walk(v, f"{prefix}{k}.")
            elif v is not None:
                flat[prefix + k] = v if isinstance(v, (bool, int, float, str)) else str(v)

    walk(to_dict(config), "")
    tb.add_hparams(flat, {}, run_name=".")  # ".": into the run's own folder, not a new one


class Run:
    """A run's parts and what it shows and writes as it goes (console, progress bar,
    TensorBoard, the eval rows of metrics.jsonl). Subclasses implement open, connect,
    eval_trigger, evaluate_now, iterate, env_steps, checkpoint_state, restore and close."""

    tb: Any
    metrics_log: MetricsLog

    def __init__(self, config: Config, run_dir: RunDir, progress: bool = True,
                 env_factory: Callable[[], Any] | None = None, callbacks: list[Callback] | None = None) -> None:
        c = config
        self.config, self.rd, self.show_progress = config, run_dir, progress
        self.env_factory = env_factory  # relayrl.train(env=...): made instead of env.id
        self.callbacks = list(callbacks or [])
        self.stop_requested = False  # a callback returned False: iterate() ends at its next check
        if c.train.torch_threads > 0:
            torch.set_num_threads(c.train.torch_threads)
        self.seeds = RunSeeds(c.seed)
        torch.manual_seed(self.seeds.base("torch"))  # network initialisation
        self.device = resolve_device(c.device)
        self.stats = EpisodeStats()
        self.stats.step_fn = self.env_steps  # where a subclass has no finer counter
        self.bar: Any = None
        self.lines: ProgressLines | None = None
        self.started = (time.perf_counter(), Progress(0, 0))  # when and where run() began: the run's sps
        self.last_eval: dict[str, Any] = {}
        self.wall_offset = 0.0
        self.t0 = time.perf_counter()
        obs_spec, act_spec = self.open()
        try:
            self._assemble(obs_spec, act_spec)
        except BaseException:  # env worker processes or Ray actors: none is left behind by a failure here
            self.close()
            raise

    def _assemble(self, obs_spec: Spec, act_spec: Spec) -> None:
        c = self.config
        spec = algorithm(c.algo)
        if spec.replay == "none":
            raise ValueError(f"algo={c.algo!r} collects into replay={spec.replay!r}; Actor + Learner runs feed "
                             "a transitions table or a rollout queue (the registry gives it a run of its own)")
        self.agent = spec.make_agent(c.agent, obs_spec, act_spec, self.device, self.seeds.generator("exploration"),
                                     c.train.total_steps)
        self.finite = FiniteWatch(c.env.num_envs, obs_spec)  # an observer of the actor, where it runs here
        table, variables = self.connect(obs_spec, act_spec)
        # A rollout queue's learner takes whole rollouts, one item each; the agent cuts its minibatches.
        items = 1 if spec.replay == "rollouts" else c.agent.batch_size
        self.learner = Learner(self.agent, table, items, self.device,
                               prioritized=c.replay.sampler == "prioritized",
                               importance_exponent=c.replay.importance_exponent,
                               priority_eps=c.replay.priority_eps, variables=variables)
        self.beta_at = linear_schedule(c.replay.importance_exponent, 1.0, c.train.total_steps)
        self.collect_only = collect_only(c)
        self.policy_saver = PolicySaver(c.train.policy_save_interval, self.agent, self.rd.policy,
                                        extra={"env_id": c.env.id})
        self.checkpointer = Checkpointer(c.train.checkpoint_interval, self.checkpoint_state, self.rd.checkpoints)
        self.sps_log = StepsPerSecondLog(c.train.log_interval, report=self.log_progress)
        self.triggers: list[IntervalTrigger] = [self.eval_trigger(), self.policy_saver, self.checkpointer,
                                                self.sps_log]

    # ---- what a subclass provides -----------------------------------------------------------
    def open(self) -> tuple[Spec, Spec]:
        """Whatever the run steps envs with; returns the observation and action specs."""
        raise NotImplementedError

    def connect(self, obs_spec: Spec, act_spec: Spec) -> tuple[Any, Any]:
        """The replay the learner samples from and the variable container it pushes to."""
        raise NotImplementedError

    def eval_trigger(self) -> IntervalTrigger:
        raise NotImplementedError

    def evaluate_now(self, p: Progress) -> None:
        raise NotImplementedError

    def settle_evals(self) -> None:
        """Wait for evaluations still in flight (none in one process)."""

    def iterate(self) -> None:
        """Collect and train up to train.total_steps, firing the triggers."""
        raise NotImplementedError

    def env_steps(self) -> int:
        raise NotImplementedError

    def checkpoint_state(self) -> dict[str, Any]:
        raise NotImplementedError

    def restore(self) -> None:
        raise NotImplementedError

    def close(self) -> None:
        """End what `open` and `connect` started, however the run ends."""

    def announce(self) -> None:
        """A line about the run's layout, once it starts."""

    # ---- shared -------------------------------------------------------------------------------
    def check_user_env(self) -> None:
        """Gymnasium's env checker, once, on a user's own env (env.check): its findings as lines."""
        c = self.config
        if c.env.check and is_user_env(c.env.id, self.env_factory):
            for line in check_env(c.env.id, c.env.kwargs, c.env.wrappers, self.env_factory, c.env.max_episode_steps):
                self.say(f"env check (env.check = false turns it off): {line}")

    def progress(self) -> Progress:
        return Progress(self.env_steps(), self.agent.train_step)

    def wall_time(self) -> float:
        return self.wall_offset + time.perf_counter() - self.t0

    def run(self, resume: bool = False) -> RunResult:
        from torch.utils.tensorboard import SummaryWriter
        from tqdm import tqdm

        c = self.config
        self.t0 = time.perf_counter()
        try:
            if not c.train.checkpoint_replay and c.train.checkpoint_interval > 0:
                self.say("train.checkpoint_replay = false: checkpoints leave the replay out; a resumed run refills it")
            if resume:
                self.restore()  # rewrites metrics.jsonl: open the log only afterwards
            self.tb = SummaryWriter(str(self.rd.tb))
            self.metrics_log = MetricsLog(self.rd.metrics)
            self.bar = tqdm(total=c.train.total_steps, unit="step", disable=None if self.show_progress else True,
                            dynamic_ncols=True, initial=self.env_steps())
            self.started = (time.perf_counter(), self.progress())
            if self.show_progress and self.bar.disable:  # no terminal: a line every 30 s instead
                self.lines = ProgressLines(self.progress_line, self.say).start()
            self.announce()
            if self.env_steps() == 0:
                log_config(self.tb, c)
                self.evaluate_now(Progress(0, 0))  # the untrained policy, before any collection
                self.policy_saver.save(Progress(0, 0))  # `relayrl eval` works from the start
            if not self.stop_requested:
                self.iterate()
            stopped = self.stop_requested and self.env_steps() < c.train.total_steps
            if stopped:
                self.say(f"a callback returned False: the run stops at env step {self.env_steps():,}")
            self.finish(self.progress())
            return RunResult(self.rd.root, self.last_eval, stopped_early=stopped)
        except NonFiniteError as e:  # found below the run (the learner): it says what the run keeps
            if e.kept:
                raise
            # the cause, where it was collected: a NaN reward is named, not the TD error it made
            raise stop(self.finite.check() or str(e), self.kept()) from None
        finally:
            if self.lines is not None:
                self.lines.stop()
            if self.bar is not None:
                self.bar.close()
            for log in (getattr(self, "tb", None), getattr(self, "metrics_log", None)):
                if log is not None:
                    log.close()
            self.close()

    def step_schedules(self, env_steps: int) -> None:
        """What follows collection: the agent's env-step schedules, the importance exponent."""
        self.agent.set_progress(env_steps)
        self.learner.importance_exponent = self.beta_at(env_steps)

    def fire_triggers(self) -> None:
        p = self.progress()
        due = [trigger for trigger in self.triggers if trigger.due(p)]
        if due or self.finite.due():
            self.check_finite(p, weights=self.policy_saver in due or self.checkpointer in due)
        for trigger in due:  # the others would find nothing due
            trigger(p)

    def check_finite(self, p: Progress, weights: bool) -> None:
        """Stop the run (NonFiniteError) at a NaN or inf in what was collected, the latest losses
        or, before a save, the weights: nothing non-finite is ever evaluated or saved."""
        finding = self.finite.check()
        where = f"by env step {p.env_steps:,} (train step {p.train_step:,})"
        if finding is None:
            loss = non_finite_metrics(self.learner.last_metrics)
            if loss is not None:
                finding = (f"{loss} {where}: check the learning rate (agent.lr and the like: too high diverges), "
                           "the reward scale and the env's observations")
        if finding is None and weights:
            name = non_finite_tensor(self.agent.state_dict())
            if name is not None:
                finding = (f"the agent's {name} held a NaN or inf {where}: check the learning rate "
                           "(too high diverges), the reward scale and the env's observations")
        if finding is not None:
            raise stop(finding, self.kept())

    def kept(self) -> str:
        """What a run stopped for a non-finite number leaves: its last checkpoint and policy."""
        ckpts = list_checkpoints(self.rd.checkpoints)
        parts = [f"the last good checkpoint (env step {int(ckpts[-1].stem.split('-')[1]):,})"] if ckpts else []
        saved = self.policy_saver.saved_at
        if saved is not None:
            parts.append(f"the policy saved at env step {saved:,}")
        elif (self.rd.policy / "policy.pt").is_file():
            parts.append("the policy saved before")
        if not parts:
            return f"nothing was saved in {self.rd.root}"
        return f"{' and '.join(parts)} {'are' if len(parts) > 1 else 'is'} kept in {self.rd.root}"

    def finish(self, p: Progress) -> None:
        """The final evaluation (unless one ran at this step), policy save, checkpoint and log."""
        self.check_finite(p, weights=True)
        if self.last_eval.get("step") != p.env_steps:
            self.evaluate_now(p)
        self.settle_evals()
        self.policy_saver.save(p)
        if self.config.train.checkpoint_interval > 0:
            self.checkpointer.save(p)
        t0, p0 = self.started
        dt = max(time.perf_counter() - t0, 1e-9)
        self.write_scalars(p, (p.env_steps - p0.env_steps) / dt, (p.train_step - p0.train_step) / dt)

    def process_state(self) -> dict[str, Any]:
        """The global RNGs (a user's env may draw from them) and the latest losses."""
        return {"global_rng": {"torch": torch.get_rng_state(), "numpy": np.random.get_state(),
                               "python": random.getstate()},
                "last_metrics": {k: v.detach().cpu() for k, v in self.learner.last_metrics.items()}}

    def load_process_state(self, state: dict[str, Any]) -> None:
        rng = state["global_rng"]
        torch.set_rng_state(rng["torch"])
        np.random.set_state(rng["numpy"])
        random.setstate(rng["python"])
        self.learner.last_metrics = dict(state["last_metrics"])

    def resume_at(self, steps: int) -> None:
        """Drop metrics rows past the checkpoint and let the triggers carry on from it."""
        kept = self.rd.truncate_metrics(after_step=steps)
        if kept and kept[-1].get("step") == steps:
            self.last_eval = kept[-1]  # a finished run resumed again needs no second final eval
        for trigger in self.triggers:
            trigger.start_at(steps)
        self.finite.checked = steps

    def say(self, text: str) -> None:
        if self.bar is not None and not self.bar.disable:
            self.bar.write(text)
        else:
            print(text, file=sys.stderr, flush=True)

    def postfix(self) -> dict[str, str]:
        """Extra fields for the progress bar."""
        return {}

    def log_progress(self, p: Progress, env_sps: float, grad_sps: float) -> None:
        """Every train.log_interval env steps: TensorBoard scalars and the progress bar. The final
        step's scalars are `finish`'s (the run's steps/s), so none is written twice."""
        scalars = None
        if p.env_steps < self.config.train.total_steps:
            scalars = self.write_scalars(p, env_sps, grad_sps)
        if self.callbacks:
            self.call_back("log", {"step": p.env_steps, "train_step": p.train_step,
                                   "wall_time_s": round(self.wall_time(), 3), **self.training_summary(),
                                   **(scalars or self.log_scalars(p, env_sps, grad_sps))})
        if self.bar is not None:
            self.bar.update(p.env_steps - self.bar.n)
            last = self.last_eval.get("average_return")
            self.bar.set_postfix(sps=f"{env_sps:.0f}", eval=f"{last:.1f}" if last is not None else "-",
                                 **self.postfix())

    def write_scalars(self, p: Progress, env_sps: float, grad_sps: float) -> dict[str, float]:
        """TensorBoard as CleanRL names it: charts/episodic_return and charts/episodic_length, one
        point per training episode at the env step it finished; then `log_scalars`, returned."""
        for step, ret, length in self.stats.take_finished():
            self.tb.add_scalar("charts/episodic_return", ret, step)
            self.tb.add_scalar("charts/episodic_length", length, step)
        scalars = self.log_scalars(p, env_sps, grad_sps)
        for k, v in scalars.items():
            self.tb.add_scalar(k, v, p.env_steps)
        return scalars

    def log_scalars(self, p: Progress, env_sps: float, grad_sps: float) -> dict[str, float]:
        """perf/sps and perf/grad_sps, losses/*, charts/epsilon (DQN), charts/learning_rate and the
        info keys' means: what TensorBoard and the callbacks' "log" rows get."""
        return {"perf/sps": env_sps, "perf/grad_sps": grad_sps, **self.learner.scalar_metrics(),
                **{f"charts/{k}": v for k, v in self.agent.scalars(p.env_steps).items()},
                **{f"charts/{k}": v for k, v in self.stats.info_means().items()}}

    def training_summary(self) -> dict[str, Any]:
        """The training episodes' side of a metrics row: their mean return, count and info means."""
        returns = self.stats.returns
        return {"train/average_return": sum(returns) / len(returns) if returns else float("nan"),
                "train/episodes": self.stats.episodes,
                **{f"train/{k}": v for k, v in self.stats.info_means().items()}}

    def progress_line(self) -> str:
        """The line printed every 30 s where there is no progress bar (no terminal)."""
        p, total = self.progress(), self.config.train.total_steps
        t0, p0 = self.started
        sps = (p.env_steps - p0.env_steps) / max(time.perf_counter() - t0, 1e-9)
        last = self.last_eval.get("average_return")
        return (f"step {p.env_steps:,}/{total:,} ({100 * p.env_steps / total:.0f}%) | {sps:,.0f} env steps/s "
                f"| last eval return {'-' if last is None else f'{last:.2f}'} | {self.wall_time():.0f}s")

    def record_eval(self, p: Progress, result: dict[str, Any], eval_s: float, wall_time_s: float | None = None,
                    extra: dict[str, Any] | None = None) -> None:
        """One metrics.jsonl row (and TensorBoard scalars, and a console line) for an evaluation."""
        wall = self.wall_time() if wall_time_s is None else wall_time_s
        row = {"step": p.env_steps, "train_step": p.train_step, **result,
               "wall_time_s": round(wall, 3), "eval_s": round(eval_s, 3), **self.training_summary(),
               **self.learner.scalar_metrics(), **(extra or {})}
        self.metrics_log.write(row)
        self.tb.add_scalar("eval/average_return", result["average_return"], p.env_steps)
        self.tb.add_scalar("eval/average_episode_length", result["average_episode_length"], p.env_steps)
        for k, v in result.items():
            if k.startswith("eval/"):
                self.tb.add_scalar(k, v, p.env_steps)
        self.last_eval = row
        self.say(f"step {p.env_steps:>9,} | eval return {result['average_return']:8.2f} "
                 f"| length {result['average_episode_length']:7.1f} | {row['wall_time_s']:7.1f}s")
        self.call_back("eval", row)

    def call_back(self, event: str, row: dict[str, Any]) -> None:
        """Each callback gets its own copy of the row with `event`; False from any stops the run.
        What a callback raises propagates (it is the user's code): the run ends there, its
        checkpoints and metrics as they were."""
        for callback in self.callbacks:
            if callback({**row, "event": event}) is False:
                self.stop_requested = True
