"""`relayrl plot`: average evaluation return against env steps, from metrics.jsonl (and, for BPTT
runs, the rollout's last-step reward beside it)."""

from __future__ import annotations

from pathlib import Path

from relayrl.errors import UserError
from relayrl.training.run_dir import RunDir


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
    fig, axes = plt.subplots(1, 2 if bptt else 1, figsize=(11 if bptt else 7, 4), squeeze=False)
    ax = axes[0][0]
    steps = [r["step"] for r in rows]
    ax.plot(steps, [r["average_return"] for r in rows], marker="o", ms=3,
            label="rollout return (batch mean)" if bptt else "eval (greedy)")
    if bptt:
        last = axes[0][1]
        last.plot(steps, [r["bptt/last_reward"] for r in rows], marker="o", ms=3, color="C2")
        last.set_xlabel("environment steps")
        last.set_ylabel("reward at the rollout's last step")
        last.grid(alpha=0.3)
    train_rows = [r for r in rows if r.get("train/average_return") is not None]
    if train_rows:
        ax.plot([r["step"] for r in train_rows], [r["train/average_return"] for r in train_rows],
                alpha=0.6, label="train (collect policy)")
    ax.set_xlabel("environment steps")
    ax.set_ylabel("average return")
    ax.set_title(rd.root.name)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path = Path(out) if out else rd.root / "returns.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
