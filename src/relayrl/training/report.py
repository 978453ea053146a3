"""What a run shows and writes as it goes: console lines, the progress bar (or a line every 30 s
without a terminal), TensorBoard, the evaluation rows of metrics.jsonl and the user's callbacks.
It never steers the run, except that a callback returning False sets `stop_requested`."""

from __future__ import annotations

import itertools
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from relayrl import atomic, interrupts
from relayrl.agents.registry import algorithm
from relayrl.config import Config, config_toml, dotted, to_dict
from relayrl.console import say
from relayrl.errors import UserError
from relayrl.metrics import EpisodeStats
from relayrl.training.heartbeat import ProgressLines
from relayrl.training.run_dir import MetricsLog, RunDir, json_row
from relayrl.training.triggers import Progress

Callback = Callable[[dict[str, Any]], Any]


def step_means(finished: list[tuple[int, float, int]]) -> list[tuple[int, float, float]]:
    """(env step, mean return, mean length) of the episodes that finished at each step, oldest
    first. One point per step, not per episode: TensorBoard draws points at one step as one
    vertical line, and 1,024 stateless envs that end their episodes together would write 1,024."""
    out: list[tuple[int, float, float]] = []
    for step, group in itertools.groupby(finished, key=lambda e: e[0]):  # `finished` is in step order
        episodes = list(group)
        out.append((step, sum(e[1] for e in episodes) / len(episodes), sum(e[2] for e in episodes) / len(episodes)))
    return out


def duration(steps: int, per_second: float) -> str:
    """How long `steps` take at `per_second`, in the largest unit that keeps it readable."""
    seconds = steps / per_second
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 2 * 3600:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def plural(n: int, noun: str) -> str:
    """"1 eval actor", "2 eval actors": a count for the console."""
    return f"{n} {noun}{'s' * (n != 1)}"


# The metric TensorBoard's HParams dashboard shows beside each run's settings (its last value).
HPARAMS_METRIC = "eval/average_return"


def log_config(tb: Any, config: Config, step: int = 0) -> None:
    """The run's config in TensorBoard: as TOML text (with each key's meaning) at env step `step`
    (a resume's settings from there on), and at the start as hparams, written into the run's own
    event file (SummaryWriter.add_hparams writes a second one, and W&B's sync_tensorboard read the
    run's scalars twice). TensorBoard keeps the first hparams it reads for a run: a resume's would
    not show. The hparams session is marked finished by `log_finished` at the run's end only: one
    that failed or stopped shows as not finished."""
    from torch.utils.tensorboard.summary import hparams

    text = config_toml(config)
    tb.add_text("config", "\n".join("    " + line for line in text.splitlines()), step)  # a markdown code block
    if step:
        return
    data = to_dict(config)
    if algorithm(config.algo).replay != "transitions":  # as its listing (config_toml): no replay keys
        data.pop("replay")
    flat = {k: v if isinstance(v, (bool, int, float, str)) else str(v)
            for k, v in dotted(data).items() if v is not None}
    experiment, session_start, _ = hparams(flat, {HPARAMS_METRIC: None})
    for summary in (experiment, session_start):
        tb.file_writer.add_summary(summary, step)


def log_finished(tb: Any, step: int) -> None:
    """The hparams session of `log_config` marked finished (the run reached its last step)."""
    from torch.utils.tensorboard.summary import hparams

    tb.file_writer.add_summary(hparams({}, {})[2], step)


class RunReport:
    """`schedules(env_steps)` gives the agent's schedules (epsilon, learning_rate); `postfix()`
    and `extra_scalars()` a driver's own progress-bar fields and TensorBoard scalars."""

    def __init__(self, config: Config, rd: RunDir, stats: EpisodeStats, *, show_progress: bool,
                 callbacks: list[Callback], progress: Callable[[], Progress], wall_time: Callable[[], float],
                 losses: Callable[[], dict[str, float]], schedules: Callable[[int], dict[str, float]],
                 postfix: Callable[[], dict[str, str]] = dict,
                 extra_scalars: Callable[[], dict[str, float]] = dict) -> None:
        self.config, self.rd, self.stats = config, rd, stats
        self.show_progress, self.callbacks = show_progress, list(callbacks)
        self.progress, self.wall_time, self.losses, self.schedules = progress, wall_time, losses, schedules
        self.postfix, self.extra_scalars = postfix, extra_scalars
        self.stop_requested = False  # a callback returned False: the driver stops at its next check
        self.interrupted: int | None = None  # the signal (Ctrl-C, SIGTERM) that asked the run to stop
        self.stopped_by: set[int] = set()  # the callbacks (by index) that returned False
        self.last_eval: dict[str, Any] = {}
        self.legend_said = False  # what an evaluation's console line holds, said above the first
        self.started = (time.perf_counter(), Progress(0, 0))  # when and where reporting began: the run's sps
        self.tb: Any = None
        self.scalars_step = -1  # the env step of the scalars TensorBoard got last (write_scalars)
        self.metrics_log: MetricsLog | None = None
        self.bar: Any = None
        self.bar_fields: dict[str, Any] = {}
        self.next_tick = 0.0  # time.monotonic() from which `tick` moves the bar again
        self.lines: ProgressLines | None = None
        self.line_from = self.started  # where the last progress line's rate began: the next measures from it

    def open(self, initial_steps: int) -> None:
        """TensorBoard, metrics.jsonl (appended to) and the progress bar, from `initial_steps`."""
        from torch.utils.tensorboard import SummaryWriter
        from tqdm import tqdm

        # A resumed run's TensorBoard hides what an earlier process wrote past the checkpoint it
        # goes on from (killed after it), as metrics.jsonl is cut back there.
        self.tb = SummaryWriter(str(self.rd.tb), purge_step=initial_steps + 1 if initial_steps else None)
        if initial_steps:  # the process before wrote the scalars of the step a resume goes on from
            self.scalars_step = initial_steps
        self.metrics_log = MetricsLog(self.rd.metrics)
        # A bar only on a terminal (tqdm's own rule): a disabled one still makes a multiprocessing
        # lock, which fixes the process's start method (a notebook's later set_start_method fails).
        if self.show_progress and sys.stderr.isatty():
            self.bar = tqdm(total=self.config.train.total_steps, unit="step", dynamic_ncols=True,
                            initial=initial_steps)
        self.started = self.line_from = (time.perf_counter(), self.progress())
        if self.show_progress and self.bar is None:  # no terminal: a line every 30 s instead
            self.lines = ProgressLines(self.progress_line, self.say).start()

    def close(self, failing: bool = False) -> None:
        """`failing`: as `close_logs`'."""
        if self.lines is not None:
            self.lines.stop()
        if self.bar is not None:
            # the bar moves every train.log_interval env steps and each second: the run's last steps too
            self.bar.update(self.progress().env_steps - self.bar.n)
            self._bar_fields()
            self.bar.close()
        close_logs([log for log in (self.tb, self.metrics_log) if log is not None], self.rd.root, failing)

    def tick(self, env_steps: int) -> None:
        """The bar between log rows, at most once a second: a slow env's rows are minutes apart."""
        if self.bar is not None and (now := time.monotonic()) >= self.next_tick:
            self.next_tick = now + 1.0
            self.bar.update(env_steps - self.bar.n)

    def request_stop(self, signum: int) -> None:
        """A signal asked the run to stop: the driver stops at its next check, as for a callback."""
        self.stop_requested, self.interrupted = True, signum
        # with checkpoints off, only the policy is saved: promising a checkpoint would mislead
        saved = "a checkpoint" if self.config.train.checkpoint_interval else \
            "the policy (train.checkpoint_interval = 0: no checkpoint)"
        self.say(f"relayrl: stopping at the end of this iteration to save {saved} ({interrupts.again(signum)})")

    def say(self, text: str) -> None:
        if self.bar is not None:
            self.bar.write(text)
        else:
            say(text)

    def run_sps(self, p: Progress) -> tuple[float, float]:
        """Env and gradient steps per second since `open`."""
        t0, p0 = self.started
        dt = max(time.perf_counter() - t0, 1e-9)
        return (p.env_steps - p0.env_steps) / dt, (p.train_step - p0.train_step) / dt

    def log_progress(self, p: Progress, env_sps: float, grad_sps: float) -> None:
        """Every train.log_interval env steps. The final step's scalars are the driver's last
        `write_scalars` (the run's steps/s), so none is written twice."""
        scalars = None
        if p.env_steps < self.config.train.total_steps:
            scalars = self.write_scalars(p, env_sps, grad_sps)
        if self.callbacks:
            self.call_back("log", {"step": p.env_steps, "train_step": p.train_step,
                                   "wall_time_s": round(self.wall_time(), 3), **self.training_summary(),
                                   **(scalars or self.log_scalars(p, env_sps, grad_sps))})
        if self.bar is not None:
            self.bar.update(p.env_steps - self.bar.n)
        self._bar_fields(sps=f"{env_sps:.0f}")

    def _bar_fields(self, **fields: str) -> None:
        """The bar's fields, which the 30 s progress line carries where there is no bar."""
        last = self.last_eval.get("average_return")
        self.bar_fields = {**self.bar_fields, **fields, "eval": f"{last:.1f}" if last is not None else "-",
                           **self.postfix()}
        if self.bar is not None:
            self.bar.set_postfix(self.bar_fields)

    def write_scalars(self, p: Progress, env_sps: float, grad_sps: float) -> dict[str, float]:
        """TensorBoard as CleanRL names it: the training episodes' return and length at the env
        step they finished (`log_episodes`), then `log_scalars`, returned."""
        self.log_episodes()
        self.scalars_step = p.env_steps
        scalars = self.log_scalars(p, env_sps, grad_sps)
        for k, v in {**scalars, **self.extra_scalars()}.items():
            self.tb.add_scalar(k, v, p.env_steps)
        return scalars

    def sync_metrics(self) -> None:
        """metrics.jsonl's rows so far on disk: before a checkpoint, which a resume trusts to
        come after them."""
        if self.metrics_log is not None:
            self.metrics_log.sync()

    def log_episodes(self) -> None:
        """The training episodes finished since the last call to TensorBoard, each step's mean at
        the env step they finished (`step_means`). Before a checkpoint too, which then holds none
        to log again after a resume."""
        if self.tb is None:
            return
        for step, ret, length in step_means(self.stats.take_finished()):
            self.tb.add_scalar("charts/episodic_return", ret, step)
            self.tb.add_scalar("charts/episodic_length", length, step)

    def log_scalars(self, p: Progress, env_sps: float, grad_sps: float) -> dict[str, float]:
        """What TensorBoard and the callbacks' "log" rows get."""
        return {"perf/sps": env_sps, "perf/grad_sps": grad_sps, **self.losses(), **self.schedule_values(p),
                **{f"charts/{k}": v for k, v in self.stats.info_means().items()}}

    def schedule_values(self, p: Progress) -> dict[str, float]:
        return {f"charts/{k}": v for k, v in self.schedules(p.env_steps).items()}

    def train_return(self) -> float:
        """The latest training episodes' mean return (NaN before the first one ends)."""
        returns = self.stats.returns
        return sum(returns) / len(returns) if returns else float("nan")

    def training_summary(self) -> dict[str, Any]:
        return {"train/average_return": self.train_return(),
                "train/episodes": self.stats.episodes,
                **{f"train/{k}": v for k, v in self.stats.info_means().items()}}

    def training_state(self) -> dict[str, Any]:
        """What an evaluation row says of training at its step: the training episodes and losses."""
        return {**self.training_summary(), **self.losses()}

    def progress_line(self) -> str:
        """The line printed every 30 s where there is no progress bar (no terminal): the rate since
        the line before (the run's since its start, a random warm-up's included, said a learning
        phase's ten times over) and the time left at it."""
        p, total = self.progress(), self.config.train.total_steps
        now, (t0, p0) = time.perf_counter(), self.line_from
        self.line_from = (now, p)
        sps = (p.env_steps - p0.env_steps) / max(now - t0, 1e-9)
        left = f" | ~{duration(total - p.env_steps, sps)} left" if sps > 0 and p.env_steps < total else ""
        train, last = self.train_return(), self.last_eval.get("average_return")
        train_shown = "-" if math.isnan(train) else f"{rounded(train):.2f}"
        last_shown = "-" if last is None else f"{rounded(last):.2f}"
        extra = "".join(f" | {k} {v}" for k, v in self.postfix().items())  # the bar's own fields (Ray's actors alive)
        return (f"step {p.env_steps:,}/{total:,} ({100 * p.env_steps / total:.0f}%) | {sps:,.0f} env steps/s{left} "
                f"| train return {train_shown} | last eval return {last_shown}{extra} | {self.wall_time():.0f}s")

    def record_eval(self, p: Progress, result: dict[str, Any], eval_s: float, wall_time_s: float | None = None,
                    extra: dict[str, Any] | None = None, at_step: dict[str, Any] | None = None) -> None:
        """`wall_time_s` and `at_step` (`training_state`) as they were at `p`, for an evaluation
        recorded later than it ran (on Ray); by default, now."""
        assert self.metrics_log is not None, "record_eval before open"
        wall = self.wall_time() if wall_time_s is None else wall_time_s
        state = self.training_state() if at_step is None else at_step
        row = {"step": p.env_steps, "train_step": p.train_step, **result,
               "wall_time_s": round(wall, 3), "eval_s": round(eval_s, 3), **state,
               **self.schedule_values(p), **(extra or {})}
        self.metrics_log.write(row)
        self.tb.add_scalar("eval/average_return", result["average_return"], p.env_steps)
        self.tb.add_scalar("eval/average_episode_length", result["average_episode_length"], p.env_steps)
        for k, v in result.items():
            if k.startswith("eval/"):
                self.tb.add_scalar(k, v, p.env_steps)
        self.last_eval = row
        if not self.legend_said:
            self.legend_said = True
            self.say(eval_legend(self.config.eval.episodes))
        self.say(eval_line(row))
        self.call_back("eval", row)

    def call_back(self, event: str, row: dict[str, Any]) -> None:
        """Each callback gets its own copy of the row with `event` (None for a value that is not a
        finite number, as metrics.jsonl's null: json.dumps(row) stays valid JSON); a false value
        from any (False, NumPy's or torch's, 0; not None, which a callback without `return` gives)
        stops the run.
        What a callback raises propagates (it is the user's code): the run ends there, its
        checkpoints and metrics as they were."""
        for i, callback in enumerate(self.callbacks):
            if i in self.stopped_by:  # a callback that returned False is not called again
                continue
            answer = callback({**json_row(row), "event": event})  # None where metrics.jsonl has null
            if answer is not None and not answer:
                self.stop_requested = True
                self.stopped_by.add(i)


def rounded(x: float, places: int = 2) -> float:
    """x rounded to `places` decimals, with -0.0 as 0.0: a return of -0.001 prints as 0.00, not -0.00."""
    return round(x, places) + 0.0


def eval_legend(episodes: int) -> str:
    """What the evaluation lines show, said before the first."""
    return (f"evaluations: mean return and length of {plural(episodes, 'episode')} of the policy acting without "
            "exploration (its greedy or mean action), then the run's wall-clock time so far")


def eval_line(row: dict[str, Any]) -> str:
    """An evaluation row's console line."""
    return (f"step {row['step']:>9,} | eval return {rounded(row['average_return']):8.2f} "
            f"| length {row['average_episode_length']:7.1f} | {row['wall_time_s']:7.1f}s")


def close_logs(logs: list[Any], folder: Path, failing: bool) -> None:
    """Close each of a run's logs (TensorBoard, metrics.jsonl). `failing`: the run is stopping on
    an error already, which a log that cannot be closed (its last lines not written: a full disk)
    must not hide; else a full disk is one line."""
    for log in logs:
        try:
            log.close()
        except OSError as e:
            if failing:
                continue
            if (full := atomic.unwritable(e, folder)) is not None:
                raise UserError(atomic.unwritable_line(full, folder)) from None
            raise
