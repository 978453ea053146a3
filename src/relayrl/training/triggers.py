"""Triggers: actions fired every `interval` env steps or gradient steps (eval, policy save,
checkpoint, steps/s log), as TF-Agents' learner triggers. Batched envs advance by B steps,
so a trigger fires once per interval boundary crossed, never more."""

from __future__ import annotations

import contextlib
import copy
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from relayrl.seeding import EVAL_STRIDE


@dataclass
class Progress:
    env_steps: int
    train_step: int


class IntervalTrigger:
    """Calls `fn(progress)` each time the counter crosses a multiple of `interval` (0: never).

    `unit` picks the counter: "env_steps" (the default, as the config's intervals) or
    "train_steps" (gradient steps, as TF-Agents' learner triggers count).
    """

    def __init__(self, interval: int, fn: Callable[[Progress], None], unit: str = "env_steps") -> None:
        if unit not in ("env_steps", "train_steps"):
            raise ValueError(f"unit={unit!r} is not valid; valid: env_steps, train_steps")
        self.interval = interval
        self.fn = fn
        self.unit = unit
        self._next = interval

    def _count(self, progress: Progress) -> int:
        return progress.env_steps if self.unit == "env_steps" else progress.train_step

    def start_at(self, count: int) -> None:
        """Skip the boundaries already passed (after a resume, or a call)."""
        if self.interval > 0:
            self._next = (count // self.interval + 1) * self.interval

    def due(self, progress: Progress) -> bool:
        return self.interval > 0 and self._count(progress) >= self._next

    def __call__(self, progress: Progress) -> bool:
        if not self.due(progress):
            return False
        self.start_at(self._count(progress))
        self.fn(progress)
        return True


class PolicySaver(IntervalTrigger):
    """Writes `folder/name` (policy.pt: what `relayrl.load_policy` reads), atomically."""

    def __init__(self, interval: int, agent: Any, folder: str | Path, unit: str = "env_steps",
                 extra: dict[str, Any] | None = None, name: str = "policy.pt") -> None:
        super().__init__(interval, self.save, unit)
        self.agent, self.folder, self.extra, self.name = agent, Path(folder), dict(extra or {}), name
        self.saved_progress: Progress | None = None  # where the policy this saver last wrote was

    def save(self, progress: Progress) -> None:
        """Write the policy as it is at `progress` (once: an evaluation, the interval and the
        run's end may all fall on one step)."""
        if progress == self.saved_progress:
            return
        self.write(progress)
        self.saved_progress = Progress(progress.env_steps, progress.train_step)

    def write(self, progress: Progress, state: dict[str, Any] | None = None,
              extra: dict[str, Any] | None = None) -> dict[str, Any]:
        """Write `state` (the agent's policy now where None), with `extra` entries; returns what
        was written (its tensors the agent's own: copy them to keep it)."""
        state = {**(self.agent.policy_state() if state is None else state), "env_steps": progress.env_steps,
                 **self.extra, **(extra or {})}
        self.write_file(state)
        return state

    def write_file(self, state: dict[str, Any]) -> None:
        from relayrl.policy_file import save_policy_file

        self.folder.mkdir(parents=True, exist_ok=True)
        save_policy_file(state, self.folder / self.name)


class BestPolicy:
    """policy/best.pt: the policy of the evaluation with the highest average return so far
    (SB3's best_model), recording that return. Checkpoints hold it (`state_dict`): a resumed run
    goes on from the checkpoint's best, not from a file a killed run wrote after that checkpoint,
    whose trajectory the resume need not repeat; a new run starts without one (a run directory
    taken over may hold an old file)."""

    def __init__(self, saver: PolicySaver) -> None:
        self.saver = saver
        self.best: float | None = None
        self.kept: dict[str, Any] | None = None  # what best.pt holds, for checkpoints

    def state_dict(self) -> dict[str, Any]:
        return {"best": self.best, "file": self.kept}

    def resume(self, saved: dict[str, Any] | None) -> None:
        """best.pt as it was at the checkpoint resumed from (`saved`, its `state_dict`), written
        again (removed where there was none yet); a checkpoint from before checkpoints held it
        (None): the file's own record is the bar."""
        path = self.saver.folder / self.saver.name
        if saved is None:
            self.kept = _read(path)  # kept from here on, so the next checkpoint holds it
            self.best = _return_of(self.kept)
            return
        self.best, self.kept = saved["best"], saved["file"]
        if self.kept is not None:
            self.saver.write_file(self.kept)
        elif self.best is None:  # no evaluation before the checkpoint: a file is of the run it left
            path.unlink(missing_ok=True)

    def offer(self, progress: Progress, average_return: float, state: dict[str, Any] | None = None) -> None:
        """Keep the evaluated policy (`state`; the agent's now where None) if its return is the best."""
        if math.isfinite(average_return) and (self.best is None or average_return > self.best):
            written = self.saver.write(progress, state, {"average_return": float(average_return)})
            self.kept = copy.deepcopy(written)  # the agent's tensors train on
            self.best = float(average_return)


def _read(path: Path) -> dict[str, Any] | None:
    """A best.pt's contents, or None (no file, or one this cannot read)."""
    from relayrl.policy_file import load_policy_file

    try:
        return load_policy_file(path) if path.is_file() else None
    except Exception:  # a damaged file is replaced at the next evaluation
        return None


def _return_of(state: dict[str, Any] | None) -> float | None:
    """The evaluation return a best.pt's contents record, or None."""
    value = (state or {}).get("average_return")
    return float(value) if isinstance(value, (int, float)) else None


class Checkpointer(IntervalTrigger):
    """Writes `state_fn()` as `folder/ckpt-<env steps>.pt` atomically, keeping the last `keep`;
    then calls `after(progress)` (a run's policy save: a crash leaves no policy older than the
    checkpoint)."""

    def __init__(self, interval: int, state_fn: Callable[[], dict[str, Any]], folder: str | Path,
                 unit: str = "env_steps", keep: int = 2, after: Callable[[Progress], None] | None = None) -> None:
        super().__init__(interval, self.save, unit)
        self.state_fn, self.folder, self.keep, self.after = state_fn, Path(folder), keep, after
        self.saved_progress: Progress | None = None  # where the checkpoint this process last wrote was

    def save(self, progress: Progress) -> None:
        from relayrl.training.checkpoint import save_checkpoint

        # A state may count its own env steps (a Ray run's replay server, ahead of the driver's
        # count by what the actors shipped since): the file is named for what it resumes from.
        state = {"env_steps": progress.env_steps, **self.state_fn()}
        save_checkpoint(self.folder, state["env_steps"], state, keep=self.keep)
        self.saved_progress = Progress(progress.env_steps, progress.train_step)
        if self.after is not None:
            self.after(progress)


def covers_boundary(steps: int, interval: int, evaluations: int) -> bool:
    """Whether an evaluation at `steps` covers a boundary of the `interval` grid (0, interval,
    2 interval, ...) that the `evaluations` so far have not: then it uses up its seed index. One
    off the grid (where a callback stopped the run, a last step between boundaries) leaves the
    index to the next, so a resume that goes on evaluates as the uninterrupted run. Without a
    grid (`interval` 0: the final evaluation only) every evaluation uses up its index."""
    return interval <= 0 or steps // interval + 1 > evaluations


class EvalSeeds:
    """The seed index of each evaluation on the `interval` grid (`covers_boundary`), and of the
    latest one, which a checkpoint keeps: a resume whose metrics.jsonl lost the row of the
    checkpoint's step evaluates that step again with the index it had, not the next one."""

    def __init__(self, interval: int) -> None:
        self.interval = interval
        self.count = 0  # indices used up
        self.last: tuple[int, int] | None = None  # (step, index) of the latest evaluation

    def index(self, steps: int) -> int:
        """The index of an evaluation at `steps`, used up where it covers a new boundary."""
        if self.last is not None and self.last[0] == steps:  # the same step again
            return self.last[1]
        index = self.count
        self.count += covers_boundary(steps, self.interval, self.count)
        self.last = (steps, index)
        return index

    def state_dict(self) -> dict[str, Any]:
        return {"eval_count": self.count, "eval_last": None if self.last is None else list(self.last)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """A checkpoint's; one written before `eval_last` was kept has only the count."""
        self.count = int(state["eval_count"])
        last = state.get("eval_last")
        self.last = None if last is None else (int(last[0]), int(last[1]))


class Evaluate(IntervalTrigger):
    """Runs `episodes` episodes of `policy_fn()` on `env`; results go to `on_result`.
    Evaluation k (`seeds`, which a resumed run restores) resets the env with seed + EVAL_STRIDE * k;
    one that covers no new boundary of the interval grid (`covers_boundary`) takes the next one's
    seed without using it up. `seconds` is how long the latest one took."""

    def __init__(self, interval: int, env: Any, policy_fn: Callable[[], Any], episodes: int = 10,
                 unit: str = "env_steps", seed: int = 0,
                 on_result: Callable[[Progress, dict[str, float]], None] | None = None,
                 network: Any = None) -> None:
        super().__init__(interval, self.evaluate, unit)
        self.env, self.policy_fn, self.episodes, self.seed = env, policy_fn, episodes, seed
        self.network = network  # the module policy_fn's policy runs: in eval mode while it is evaluated
        self.on_result = on_result
        self.seeds = EvalSeeds(interval)
        self.seconds = 0.0

    def evaluate(self, progress: Progress) -> None:
        from relayrl.nn.modes import evaluating
        from relayrl.training.evaluate import evaluate

        t0 = time.perf_counter()
        index = self.seeds.index(self._count(progress))
        with contextlib.nullcontext() if self.network is None else evaluating(self.network):
            result = evaluate(self.env, self.policy_fn(), self.episodes, seed=self.seed + EVAL_STRIDE * index)
        self.seconds = time.perf_counter() - t0
        if self.on_result is not None:
            self.on_result(progress, result)


class StepsPerSecondLog(IntervalTrigger):
    """Env steps/s and gradient steps/s since the previous log (TF-Agents' StepPerSecondLogTrigger):
    `report(progress, env_sps, grad_sps)` gets them; by default a line goes to `log`."""

    def __init__(self, interval: int, unit: str = "env_steps", log: Callable[[str], None] | None = None,
                 report: Callable[[Progress, float, float], None] | None = None) -> None:
        super().__init__(interval, self.log_rates, unit)
        self.log = log or (lambda text: print(text, file=sys.stderr, flush=True))
        self.report = report or self._line
        self.reset(Progress(0, 0))

    def reset(self, progress: Progress) -> None:
        """Count the rates from `progress`, now (where collection starts)."""
        self._t, self._last = time.perf_counter(), progress

    def log_rates(self, progress: Progress) -> None:
        now = time.perf_counter()
        dt = max(now - self._t, 1e-9)
        env_sps, grad_sps = ((progress.env_steps - self._last.env_steps) / dt,
                             (progress.train_step - self._last.train_step) / dt)
        self._t, self._last = now, Progress(progress.env_steps, progress.train_step)
        self.report(progress, env_sps, grad_sps)

    def _line(self, progress: Progress, env_sps: float, grad_sps: float) -> None:
        self.log(f"step {progress.env_steps:,} | train step {progress.train_step:,} | "
                 f"{env_sps:.1f} env steps/s | {grad_sps:.1f} grad steps/s")
