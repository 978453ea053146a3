"""`relayrl plot`: average evaluation return against env steps, from metrics.jsonl (and, for BPTT
runs, the rollout's last-step reward beside it; for DQN runs, episode length, loss and mean Q,
the four curves of the Mario tutorial's logger)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from relayrl.errors import UserError
from relayrl.training.run_dir import RunDir

Rows = list[dict[str, Any]]


def plot_run(run_dir: str | Path, out: str | Path | None = None) -> Path:
    rd = RunDir(run_dir)
    rd.require()
    rows = [r for r in rd.read_metrics() if r.get("average_return") is not None]
    if not rows:
        raise UserError(f"{str(rd.metrics)!r} has no evaluations yet; train first")
    import matplotlib

    matplotlib.use("Agg")  # no display needed
    import matplotlib.pyplot as plt

    # BPTT runs (algo = "bptt") log training rollouts, not evaluations; like TorchRL's
    # tutorial, they get a second panel with the reward at the rollout's last step.
    bptt = rows[0].get("bptt/last_reward") is not None
    q_learning = not bptt and any(r.get("losses/q") is not None for r in rows)
    shape = (1, 2) if bptt else (2, 2) if q_learning else (1, 1)
    fig, axes = plt.subplots(*shape, figsize=(7 * shape[1] ** 0.8, 4 * shape[0]), squeeze=False)
    panels = axes.ravel()
    _returns(panels[0], rows, bptt)
    panels[0].set_title(rd.root.name)
    if bptt:
        _curve(panels[1], rows, "bptt/last_reward", "reward at the rollout's last step", color="C2")
    if q_learning:
        _curve(panels[1], rows, "average_episode_length", "average episode length (eval)", color="C2")
        _curve(panels[2], rows, "losses/loss", "loss (latest batch)", color="C3")
        _curve(panels[3], rows, "losses/q", "mean Q of the batch's actions", color="C4")
    fig.tight_layout()
    path = Path(out) if out else rd.root / "returns.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _returns(ax: Any, rows: Rows, bptt: bool) -> None:
    ax.plot([r["step"] for r in rows], [r["average_return"] for r in rows], marker="o", ms=3,
            label="rollout return (batch mean)" if bptt else "eval (greedy)")
    train_rows = [r for r in rows if r.get("train/average_return") is not None]
    if train_rows:
        ax.plot([r["step"] for r in train_rows], [r["train/average_return"] for r in train_rows],
                alpha=0.6, label="train (collect policy)")
    ax.set_xlabel("environment steps")
    ax.set_ylabel("average return")
    ax.grid(alpha=0.3)
    ax.legend()


def _curve(ax: Any, rows: Rows, key: str, label: str, color: str) -> None:
    points = [(r["step"], r[key]) for r in rows if r.get(key) is not None]
    ax.plot([s for s, _ in points], [v for _, v in points], marker="o", ms=3, color=color)
    ax.set_xlabel("environment steps")
    ax.set_ylabel(label)
    ax.grid(alpha=0.3)
