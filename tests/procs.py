"""Process states read from /proc (Linux, no psutil), for tests that check no process outlives a run."""

from __future__ import annotations

import os


def proc_state(pid: int) -> tuple[str, int] | None:
    """(state, parent pid) of a process from /proc; None once it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            state, ppid = f.read().rsplit(")", 1)[1].split()[:2]
    except (OSError, ValueError):
        return None
    return state, int(ppid)


def running(pid: int) -> bool:
    """Not gone, and not a zombie (exited, not yet reaped)."""
    st = proc_state(pid)
    return st is not None and st[0] != "Z"


def children_running(pid: int) -> set[int]:
    """Processes whose parent is `pid` and that have not exited (zombies left out)."""
    found = {int(d): proc_state(int(d)) for d in os.listdir("/proc") if d.isdigit()}
    return {p for p, st in found.items() if st is not None and st[1] == pid and st[0] != "Z"}


def process_tree(root: int) -> set[int]:
    """`root` and every process below it."""
    children: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit() and (st := proc_state(int(d))) is not None:
            children.setdefault(st[1], []).append(int(d))
    out, todo = set(), [root]
    while todo:
        p = todo.pop()
        out.add(p)
        todo.extend(children.get(p, []))
    return out


def alive(pids: set[int]) -> set[int]:
    """Those of `pids` still running."""
    return {p for p in pids if running(p)}
