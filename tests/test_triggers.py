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
