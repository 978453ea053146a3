"""The direct driver: an algorithm that trains by itself (registry `replay = "none"`: BPTT
through a differentiable env) writes its run directory through this: metrics rows with the
evaluations every run's have (at step 0, every eval.interval env steps and at the end),
TensorBoard, the config, and the policy file at the end (at the iteration a Ctrl-C or SIGTERM
stopped it, too: its runs have no checkpoints). No actor, replay or learner."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import Any, cast

import numpy as np

from relayrl import atomic, interrupts
from relayrl.agents.registry import algorithm
from relayrl.config import Config
from relayrl.config_checks import TrainerSection
from relayrl.console import say
from relayrl.errors import UserError
from relayrl.policy_file import save_policy_file
from relayrl.seeding import RunSeeds
from relayrl.training.evaluate import make_eval_env
from relayrl.training.history import record_process
from relayrl.training.lifecycle import RunResult
from relayrl.training.process import resolve_device
from relayrl.training.report import close_logs, eval_legend, eval_line, log_config, log_finished
from relayrl.training.run_dir import MetricsLog, RunDir
from relayrl.training.triggers import Evaluate, Progress


class DirectDriver:
    """The trainer's config is checked when the config is (`Config.validate`); its runs are
    not resumable (Algorithm.resumable)."""

    def __init__(self, config: Config, rd: RunDir) -> None:
        self.entry = algorithm(config.algo)
        self.trainer = self.entry.direct_trainer()
        self.config, self.rd = config, rd

    def train(self, resume: bool = False) -> RunResult:
        from torch.utils.tensorboard import SummaryWriter

        c = self.config
        device = resolve_device(c.device)
        rows: list[dict[str, Any]] = []
        signals: list[int] = []  # the first Ctrl-C / SIGTERM: stop after this iteration, keep the policy
        per_iteration = cast(TrainerSection, c.agent).iteration_steps()
        iterations = c.train.total_steps // per_iteration
        total = iterations * per_iteration
        window: list[dict[str, float]] = []  # the iterations' scalars since the last row
        history: list[dict[str, float]] = []
        state_now: Callable[[], dict[str, Any]] | None = None  # the policy's state at the step reached
        t0 = time.perf_counter()
        log, tb = MetricsLog(self.rd.metrics), SummaryWriter(str(self.rd.tb))
        try:
            eval_env = make_eval_env(c.env.id, c.eval.episodes, device=device)
        except BaseException:
            close_logs([log, tb], self.rd.root, failing=True)
            raise

        def policy() -> Any:
            assert state_now is not None  # evaluations run from on_iteration, which sets it
            return self.entry.policy_module().load(state_now(), device, True, None)

        def record(p: Progress, result: dict[str, float]) -> None:
            # the window's means, but a schedule's value (charts/) where the row is, as every run's rows
            means = {k: (window[-1][k] if k.startswith("charts/") else float(np.mean([w[k] for w in window])))
                     for k in window[0]} if window else {}
            row = {"step": p.env_steps, "train_step": p.train_step, **result,
                   "wall_time_s": round(time.perf_counter() - t0, 3), "eval_s": round(evaluator.seconds, 3),
                   **means, **(self.trainer.final_scalars(history) if p.env_steps == total and history else {})}
            log.write(row)
            rows.append(row)
            tb.add_scalar("eval/average_return", result["average_return"], p.env_steps)
            tb.add_scalar("eval/average_episode_length", result["average_episode_length"], p.env_steps)
            window.clear()
            if len(rows) == 1:
                say(eval_legend(c.eval.episodes))
            say(eval_line(row))  # with progress=False too, as every run's

        # where and with which seeds every run evaluates: at step 0, at the first iteration at or
        # past each multiple of eval.interval, and at the end (eval.interval 0: the end only)
        evaluator = Evaluate(c.eval.interval, eval_env, policy, c.eval.episodes,
                             seed=RunSeeds(c.seed).base("evaluation"), on_result=record)

        def on_iteration(steps: int, scalars: dict[str, float], state: Callable[[], dict[str, Any]]) -> None:
            nonlocal state_now
            state_now = state
            for name, value in scalars.items():
                tb.add_scalar(name, value, steps)
            if scalars:
                window.append(scalars)
                history.append(scalars)
            p = Progress(steps, steps // per_iteration)
            if steps == total or (steps == 0 and c.eval.interval > 0):
                evaluator.start_at(steps)
                evaluator.evaluate(p)
            else:
                evaluator(p)

        def on_signal(signum: int) -> None:
            signals.append(signum)
            say("relayrl: stopping at the end of this iteration to save the policy (no checkpoints for "
                f"algo={c.algo!r}; {interrupts.again(signum)})")

        try:
            record_process(self.rd.history, 0, [])  # its runs start at step 0: they are not resumed
            log_config(tb, c)
            with interrupts.stop_request(on_signal):
                state = self.trainer.train(c.agent, iterations, c.seed, device, c.train.torch_threads, on_iteration,
                                           lambda: bool(signals))
        except Exception as e:
            if gone := self.rd.gone_line():  # whatever failed for it (TensorBoard's next write)
                raise UserError(gone) from None
            if (full := atomic.unwritable(e, self.rd.root)) is not None:  # metrics.jsonl's or TensorBoard's write
                raise UserError(f"{atomic.unwritable_line(full, self.rd.root)}; algo={c.algo!r} runs have no "
                                "checkpoints: a new run starts over") from None
            raise
        finally:
            eval_env.close()
            failing = sys.exc_info()[0] is not None
            if not failing and not signals:
                log_finished(tb, state["env_steps"])
            close_logs([log, tb], self.rd.root, failing=failing)
        if gone := self.rd.gone_line():
            raise UserError(gone)
        save_policy_file(state, self.rd.policy / "policy.pt")
        if signals:  # one in the last iteration too: the run is whole, and the caller's loop still stops
            interrupts.redeliver(signals[0], f"the run stopped at env step {state['env_steps']:,}; its policy and "
                                 f"metrics are in {str(self.rd.root)!r} (algo={c.algo!r} runs have no "
                                 "checkpoints: a new run starts over)")
        return RunResult(self.rd.root, rows[-1] if rows else {})

    def close(self) -> None:
        """Nothing outlives `train`: the trainer runs in this process, on its own envs."""
