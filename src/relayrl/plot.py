"""`relayrl plot`: average evaluation return against env steps, from metrics.jsonl (and, for BPTT
runs, the rollout's last-step reward beside it; for DQN runs, episode length, loss and mean Q,
the four curves of the Mario tutorial's logger; a panel per `env.info_keys` key). Several runs
(a sweep's seeds or settings) share one panel of their evaluation returns; runs that differ only
in their seed are one curve, their mean, with a band from their lowest to their highest."""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from relayrl import atomic
from relayrl.config import load_toml
from relayrl.errors import ConfigError, UserError
from relayrl.paths import output_path, writing
from relayrl.training.run_dir import RunDir

Rows = list[dict[str, Any]]


def plot_run(run_dir: str | Path | Sequence[str | Path], out: str | Path | None = None) -> Path:
    """A PNG (or any format matplotlib writes, by `out`'s extension) of the run's curves, written
    as RUN_DIR/returns.png by default; several run directories (or a folder holding them): their
    evaluation returns in one panel, each labelled with its folder's name (runs that differ only
    in their seed as one mean curve in a min-to-max band, `seed_groups`), as compare.png in their
    common parent folder."""
    if not isinstance(run_dir, (str, Path)):
        return _compare(_given_runs(run_dir), out)
    rd = RunDir(run_dir)
    if rd.root.is_dir() and not rd.config.exists() and (inside := _runs_inside(rd.root)):  # a sweep's folder
        return _compare(inside, out if out is not None else rd.root / "compare.png", base=rd.root)
    if out is not None and Path(out).resolve() != rd.root.resolve() and RunDir(out).metrics.is_file():
        # plot_run(a, b), as `relayrl plot A B` is written: b's returns.png was replaced by a's plot
        raise UserError(f"out={str(out)!r} is another run's directory: to plot several runs in one panel give "
                        f"them as one list, plot_run([{str(run_dir)!r}, {str(out)!r}])")
    rows = _evaluations(rd)

    # BPTT runs (algo = "bptt"): like TorchRL's tutorial, a second panel with the training
    # rollouts' reward at their last step (a row's mean over its iterations; none at step 0).
    bptt = any(r.get("bptt/last_reward") is not None for r in rows)
    curves = panels_for(rows, bptt)
    # env.info_keys (Mario's x_pos): eval/<key> per evaluation, train/<key> over the episode window
    info_keys = sorted({k[5:] for r in rows for k in r if k.startswith("eval/")})
    panels_n = 1 + len(curves) + len(info_keys)
    shape = (1, 1) if panels_n == 1 else ((panels_n + 1) // 2, 2)
    fig = _figure(figsize=(7 * shape[1] ** 0.8, 4 * shape[0]))
    axes = fig.subplots(*shape, squeeze=False)
    panels = axes.ravel()
    _returns(panels[0], rows)
    panels[0].set_title(rd.root.name)
    for i, (key, label) in enumerate(curves, start=1):
        _curve(panels[i], rows, key, label, color=f"C{i + 1}")
    for i, key in enumerate(info_keys, start=1 + len(curves)):
        _curve(panels[i], rows, f"eval/{key}", f"{key} at episode end", color="C0", legend="eval (greedy)")
        _curve(panels[i], rows, f"train/{key}", f"{key} at episode end", color="C1", legend="train (collect policy)")
        panels[i].legend()
    for ax in panels[panels_n:]:
        ax.set_visible(False)
    return _save(fig, output_path(out, rd.root / "returns.png"))


def _runs_inside(folder: Path, depth: int = 3) -> list[RunDir]:
    """The run directories inside `folder`, by path: a sweep's `lr1/seed0` too, `depth` levels
    down at most (a run directory's own folders are not searched)."""
    found: list[RunDir] = []
    for d in sorted(folder.iterdir()):
        if not d.is_dir():
            continue
        if (d / "config.toml").is_file():
            found.append(RunDir(d))
        elif depth > 1:
            found += _runs_inside(d, depth - 1)
    return found


# Files a plot is written as: `relayrl plot sweep/*` also matches the compare.png plotted before.
_PLOT_FILES = (".png", ".svg", ".pdf", ".jpg", ".jpeg", ".eps", ".ps", ".tif", ".tiff", ".webp")


def _given_runs(given: Sequence[str | Path]) -> list[RunDir]:
    """The run directories given, each once; a plot file among them (a glob's) left out."""
    runs: dict[Path, RunDir] = {}
    for d in given:
        rd = RunDir(d)
        if rd.root.is_file() and rd.root.suffix.lower() in _PLOT_FILES:
            continue
        if rd.root.resolve() in runs:
            print(f"{str(rd.root)!r} is given twice: drawn once", file=sys.stderr)
        runs.setdefault(rd.root.resolve(), rd)
    return list(runs.values())


def _compare(runs: list[RunDir], out: str | Path | None, base: Path | None = None) -> Path:
    """One panel: each run's evaluation returns against env steps; named by their paths below
    `base` (a sweep's folder) where given, else by their folders' names."""
    if not runs:
        raise UserError("no run directory given: give one or more")
    for rd in runs:
        rd.require()
    found = [_evaluation_rows(rd) for rd in runs]
    if not any(found):
        _evaluations(runs[0])  # says why it has none
    # a run with none yet (one under way, or stopped before its first) is left out, not the plot
    for rd, run_rows in zip(runs, found, strict=True):
        if not run_rows:
            print(f"{str(rd.metrics)!r} has no evaluations yet: left out of the plot", file=sys.stderr)
    runs, rows = [rd for rd, r in zip(runs, found, strict=True) if r], [r for r in found if r]
    parents = {rd.root.resolve().parent for rd in runs}
    if out is None and len(parents) > 1:
        raise UserError("the run directories are in different folders: give --out PATH for the plot")
    names = [rd.root.relative_to(base).as_posix() if base is not None else rd.root.name for rd in runs]
    if len(set(names)) < len(names):  # the same name in several folders: their paths tell them apart
        names = [str(rd.root) for rd in runs]
    saved = [_saved_toml(rd) for rd in runs]  # each config.toml read once: envs, seed groups, seeds
    envs = {name: env for name, toml in zip(names, saved, strict=True) if (env := _env_id(toml)) is not None}
    if len(set(envs.values())) > 1:  # returns of different envs share no scale
        print(f"the runs are on different envs ({', '.join(f'{n}: {e}' for n, e in envs.items())}): their "
              "returns are drawn on one axis all the same", file=sys.stderr)
    fig = _figure(figsize=(8, 5))
    ax = fig.subplots()
    for group in seed_groups(runs, saved):
        seeds = [(saved[i] or {}).get("seed") for i in group]
        _say_factories_alike([names[i] for i in group], _env_id(saved[group[0]]))
        _group_curve(ax, [names[i] for i in group], [rows[i] for i in group], seeds)
    _steps_axis(ax, [r["step"] for run_rows in rows for r in run_rows])
    ax.set_ylabel("average return (eval)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    return _save(fig, output_path(out, runs[0].root.parent / "compare.png"))  # as given: relative stays relative


def _say_factories_alike(names: list[str], env_id: str | None) -> None:
    """A line where runs drawn as one setting's seeds were trained on an env factory given in
    Python that their config.toml records without its contents (a lambda, a closure; a partial
    is recorded with its arguments): they may be different envs."""
    from relayrl.envs.resolve import names_python_factory

    if len(names) > 1 and env_id is not None and names_python_factory(env_id) and ":<partial(" not in env_id:
        print(f"{', '.join(names)} were trained on env factories given in Python (env.id={env_id!r}) that their "
              "config.toml cannot tell apart: drawn as seeds of one setting", file=sys.stderr)


def _saved_toml(rd: RunDir) -> dict[str, Any] | None:
    """The run's config.toml as read, or None where it cannot be read."""
    try:
        return load_toml(rd.config)
    except (ConfigError, OSError):
        return None


def _env_id(saved: dict[str, Any] | None) -> str | None:
    """The env.id a config.toml as read (`_saved_toml`) records, or None."""
    env = (saved or {}).get("env", {})
    return str(env["id"]) if isinstance(env, dict) and "id" in env else None


def seed_groups(runs: list[RunDir], saved: list[dict[str, Any] | None] | None = None) -> list[list[int]]:
    """The runs (by index, in order of first appearance) whose config.toml are the same but for
    their seed: one setting's seeds, drawn as one curve. A run without a readable config is its
    own group. `saved`: their config.toml as read already (`_saved_toml`), else read here."""
    tomls = saved if saved is not None else [_saved_toml(rd) for rd in runs]
    groups: dict[str, list[int]] = {}
    for i, toml in enumerate(tomls):
        key = f"run {i}" if toml is None else json.dumps({k: v for k, v in toml.items() if k != "seed"},
                                                          sort_keys=True, default=str)
        groups.setdefault(key, []).append(i)
    return list(groups.values())


def _group_curve(ax: Any, names: list[str], rows: list[Rows], seeds: list[Any]) -> None:
    """One run's evaluation returns; several seeds' mean at the env steps all of them evaluated at,
    in a band from the lowest to the highest (each run on its own where they share no step). Where
    that ends before a run's last evaluation (a seed still running) or runs share a seed (copies
    of one run), a line says so."""
    returns = [{r["step"]: r["average_return"] for r in run_rows} for run_rows in rows]
    steps = sorted(set.intersection(*(set(by_step) for by_step in returns)))
    if len(rows) == 1 or not steps:
        for name, by_step in zip(names, returns, strict=True):
            ax.plot(list(by_step), list(by_step.values()), marker="o", ms=3, label=name)
        return
    values = [[by_step[s] for by_step in returns] for s in steps]
    shown = ", ".join(names if len(names) <= 3 else [*names[:2], "..."])
    if len(shown) > 48:  # runs/<algo>-<env>-s<seed>-<date>-<time> names: a legend wider than the axes
        shown = f"{names[0]} and {len(names) - 1} more"
    distinct = len(set(map(str, seeds))) == len(seeds)
    what = f"{len(names)} seeds" if distinct else f"{len(names)} runs, seeds {', '.join(map(str, seeds))}"
    if not distinct:
        print(f"{', '.join(names)} share a seed ({', '.join(map(str, seeds))}): their band is not a spread over "
              "seeds", file=sys.stderr)
    if (longest := max(max(by_step) for by_step in returns)) > steps[-1]:
        print(f"{', '.join(names)}: their mean is drawn to env step {steps[-1]:,}, the last all {len(names)} "
              f"evaluated at (the longest goes to {longest:,})", file=sys.stderr)
    line, = ax.plot(steps, [sum(v) / len(v) for v in values], marker="o", ms=3,
                    label=f"{shown} ({what}: mean, min to max)")
    ax.fill_between(steps, [min(v) for v in values], [max(v) for v in values], color=line.get_color(), alpha=0.2)


def _evaluation_rows(rd: RunDir) -> Rows:
    return [r for r in rd.read_metrics() if r.get("average_return") is not None]


def _evaluations(rd: RunDir) -> Rows:
    rd.require()
    rows = _evaluation_rows(rd)
    if not rows:
        raise UserError(f"{str(rd.metrics)!r} has no evaluations yet; {_why_none(rd)}")
    return rows


def _why_none(rd: RunDir) -> str:
    """What to do about a run without evaluations: "train first" misleads for a run under way
    with eval.interval = 0, whose only evaluation is its last."""
    try:
        interval = load_toml(rd.config).get("eval", {}).get("interval")
    except ConfigError:
        interval = None
    if interval == 0:
        return "its eval.interval is 0, so it evaluates once, at the end of training: plot it then"
    return "train first"


def _figure(figsize: tuple[float, float]) -> Any:
    """A figure of its own, made without pyplot: the caller's backend (a notebook's inline one)
    is never switched, and nothing is left open in pyplot's list of figures."""
    from matplotlib.figure import Figure

    return Figure(figsize=figsize)


def _save(fig: Any, path: Path) -> Path:
    """`fig` into `path` in the format its extension names, atomically."""
    fig.tight_layout()
    kind = path.suffix[1:].lower() or "png"
    if kind not in fig.canvas.get_supported_filetypes():
        raise UserError(f"--out {str(path)!r}: .{kind} is not an image format matplotlib writes; "
                        f"valid: {', '.join(sorted(fig.canvas.get_supported_filetypes()))}")
    # a plot already there stays until the new one is complete
    with writing(path), atomic.replacing(path, ".tmp-" + path.name) as tmp:
        fig.savefig(tmp, dpi=100, format=kind)
    return path


def panels_for(rows: Rows, bptt: bool) -> list[tuple[str, str]]:
    """(metrics key, axis label) of each panel after the returns'."""
    if bptt:
        return [("bptt/last_reward", "reward at the rollout's last step")]
    if not any(r.get("losses/q") is not None for r in rows):  # PPO
        return []
    # DQN's TD loss, or SAC's critic loss: the Q-learning half of an actor-critic
    loss = "losses/loss" if any(r.get("losses/loss") is not None for r in rows) else "losses/critic_loss"
    return [("average_episode_length", "average episode length (eval)"),
            (loss, f"{'critic ' * (loss != 'losses/loss')}loss (latest batch)"),
            ("losses/q", "mean Q of the batch's actions")]


def _steps_axis(ax: Any, steps: list[int]) -> None:
    ax.set_xlabel("environment steps")
    if steps and min(steps) == max(steps):  # one evaluation: an axis from 0, not around one point,
        ax.set_xlim(0, 1.05 * max(steps) or 1)  # with the point inside it, not on its edge


def _returns(ax: Any, rows: Rows) -> None:
    ax.plot([r["step"] for r in rows], [r["average_return"] for r in rows], marker="o", ms=3, label="eval (greedy)")
    train_rows = [r for r in rows if r.get("train/average_return") is not None]
    if train_rows:
        ax.plot([r["step"] for r in train_rows], [r["train/average_return"] for r in train_rows],
                alpha=0.6, marker="o", ms=2, label="train (collect policy)")
    _steps_axis(ax, [r["step"] for r in rows])
    ax.set_ylabel("average return")
    ax.grid(alpha=0.3)
    ax.legend()


def _curve(ax: Any, rows: Rows, key: str, label: str, color: str, legend: str | None = None) -> None:
    points = [(r["step"], r[key]) for r in rows if r.get(key) is not None]
    ax.plot([s for s, _ in points], [v for _, v in points], marker="o", ms=3, color=color, label=legend)
    _steps_axis(ax, [s for s, _ in points])
    ax.set_ylabel(label)
    ax.grid(alpha=0.3)
