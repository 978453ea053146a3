"""Triggers fire once per interval boundary crossed, at any step size, and skip after a resume."""

from relayrl.training.triggers import IntervalTrigger, Progress


def fired_at(interval, steps, start=0):
    seen = []
    t = IntervalTrigger(interval, lambda p: seen.append(p.env_steps))
    if start:
        t.start_at(start)
    for s in steps:
        t(Progress(s, 0))
    return seen


def test_fires_at_each_boundary_with_single_steps():
    assert fired_at(3, range(1, 11)) == [3, 6, 9]


def test_batched_steps_fire_once_per_crossing_never_twice():
    # 7 envs step 7 at a time; interval 10: boundaries 10, 20, 30, 40 crossed at 14, 21, 35, 42
    assert fired_at(10, range(7, 50, 7)) == [14, 21, 35, 42]
    # one jump across several boundaries fires once
    assert fired_at(10, [35]) == [35]


def test_zero_interval_never_fires_and_resume_skips_passed_boundaries():
    assert fired_at(0, range(100)) == []
    assert fired_at(10, [25, 30, 41], start=25) == [30, 41]


def test_train_step_triggers_fire_inside_learner_run(tmp_path):
    import numpy as np
    import torch

    from relayrl.agents.dqn import DQNAgent, DQNConfig
    from relayrl.envs import make_env
    from relayrl.export import load_policy
    from relayrl.policies import RandomPolicy
    from relayrl.replay import Fifo, MinSize, Table, TransitionWriter, Uniform
    from relayrl.training.actor import Actor
    from relayrl.training.checkpoint import list_checkpoints
    from relayrl.training.learner import Learner
    from relayrl.training.triggers import Checkpointer, Evaluate, PolicySaver, StepsPerSecondLog

    env = make_env("CartPole-v1")
    agent = DQNAgent(env.observation_spec, env.action_spec, DQNConfig(hidden=[8], batch_size=4),
                     torch.device("cpu"), np.random.default_rng(0))
    table = Table("t", 100, Uniform(), Fifo(), MinSize(4), seed=0)
    actor = Actor(env, RandomPolicy(env.action_spec, np.random.default_rng(0)),
                  [TransitionWriter(table, 1, env.observation_spec, env.action_spec, gamma=0.99)], seed=0)
    actor.collect(20)
    logs, evals = [], []
    triggers = [
        PolicySaver(5, agent, tmp_path / "policy", unit="train_steps"),
        Checkpointer(4, lambda: {"agent": agent.state_dict()}, tmp_path / "ck", unit="train_steps"),
        Evaluate(6, make_env("CartPole-v1", 2), agent.eval_policy, episodes=2, unit="train_steps",
                 on_result=lambda p, r: evals.append((p.train_step, r["episodes"]))),
        StepsPerSecondLog(3, unit="train_steps", log=logs.append),
    ]
    learner = Learner(agent, table, 4, torch.device("cpu"), triggers=triggers, env_steps=lambda: actor.env_steps)
    learner.learn(12)
    assert evals == [(6, 2), (12, 2)]
    assert len(logs) == 4 and logs[0].startswith("step 20 | train step 3 |")
    assert [p.name for p in list_checkpoints(tmp_path / "ck")] == ["ckpt-000000000020.pt"]  # same env step
    assert load_policy(tmp_path)(torch.zeros(3, 4)).shape == (3,)


class _WeightAgent:
    """An agent whose policy is one number, `weight`."""

    weight = 0.0

    def policy_state(self):
        import torch

        return {"kind": "test", "weight": torch.tensor(self.weight)}


def test_best_pt_keeps_the_highest_evaluation_and_a_resume_goes_on_from_its_bar(tmp_path):
    import torch

    from relayrl.training.triggers import BestPolicy, PolicySaver, Progress

    agent = _WeightAgent()
    best = BestPolicy(PolicySaver(0, agent, tmp_path, name="best.pt"))
    assert best.best is None and not (tmp_path / "best.pt").exists()
    for step, weight, ret in ((0, 0.0, 10.0), (100, 1.0, 30.0), (200, 2.0, 20.0), (300, 3.0, float("nan"))):
        agent.weight = weight
        best.offer(Progress(step, step), ret)
    saved = torch.load(tmp_path / "best.pt", weights_only=True)
    assert (saved["env_steps"], saved["average_return"], float(saved["weight"])) == (100, 30.0, 1.0)
    at_checkpoint = best.state_dict()
    again = BestPolicy(PolicySaver(0, agent, tmp_path, name="best.pt"))
    assert again.best is None  # a new run in a folder taken over: the old file's bar is not its
    again.resume(None)  # a resumed run's, from a checkpoint that holds no best: the file's record
    assert again.best == 30.0
    again.resume(at_checkpoint)  # from one that holds it
    assert again.best == 30.0 and torch.load(tmp_path / "best.pt", weights_only=True)["env_steps"] == 100
    again.offer(Progress(400, 400), 25.0)
    assert torch.load(tmp_path / "best.pt", weights_only=True)["env_steps"] == 100
    again.offer(Progress(500, 500), 31.0, state={"kind": "test", "weight": torch.tensor(9.0)})  # one evaluated earlier
    saved = torch.load(tmp_path / "best.pt", weights_only=True)
    assert (saved["env_steps"], float(saved["weight"])) == (500, 9.0)


def test_a_resume_puts_back_the_best_pt_of_its_checkpoint_not_one_a_killed_run_wrote_after_it(tmp_path):
    """A run killed after a better evaluation than its last checkpoint's: best.pt held a policy of a
    trajectory the resume (not bit for bit: an env that cannot be pickled, a --set) did not repeat."""
    import torch

    from relayrl.training.triggers import BestPolicy, PolicySaver, Progress

    agent = _WeightAgent()
    best = BestPolicy(PolicySaver(0, agent, tmp_path, name="best.pt"))
    best.offer(Progress(100, 100), 10.0)
    agent.weight = 5.0  # trained on: the kept policy is the one evaluated, not the agent's tensors now
    at_checkpoint = best.state_dict()
    best.offer(Progress(200, 200), 50.0)  # after the checkpoint, then killed
    resumed = BestPolicy(PolicySaver(0, agent, tmp_path, name="best.pt"))
    resumed.resume(at_checkpoint)
    saved = torch.load(tmp_path / "best.pt", weights_only=True)
    assert (resumed.best, saved["env_steps"], saved["average_return"], float(saved["weight"])) == (10.0, 100, 10.0, 0.0)
    none_yet = BestPolicy(PolicySaver(0, agent, tmp_path, name="best.pt"))
    none_yet.resume({"best": None, "file": None})  # a checkpoint before any evaluation
    assert none_yet.best is None and not (tmp_path / "best.pt").exists()


def test_a_second_resume_after_a_checkpoint_of_an_earlier_version_keeps_best_pt(tmp_path):
    """Resumed from a checkpoint without best.pt's contents, the run kept the bar only: its next
    checkpoint held no file, and a resume from that one deleted best.pt."""
    import torch

    from relayrl.training.triggers import BestPolicy, PolicySaver, Progress

    agent = _WeightAgent()
    BestPolicy(PolicySaver(0, agent, tmp_path, name="best.pt")).offer(Progress(100, 100), 10.0)
    first = BestPolicy(PolicySaver(0, agent, tmp_path, name="best.pt"))
    first.resume(None)  # an earlier version's checkpoint
    second = BestPolicy(PolicySaver(0, agent, tmp_path, name="best.pt"))
    second.resume(first.state_dict())  # this version's, written after the first resume
    saved = torch.load(tmp_path / "best.pt", weights_only=True)
    assert (second.best, saved["env_steps"], saved["average_return"]) == (10.0, 100, 10.0)
