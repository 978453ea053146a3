"""Distributed training on Ray: replay server, variable container, rollout and eval actors.

`relayrl train PRESET --set distributed.num_actors=K` runs the same config and agent code
with the replay Table and the VariableContainer in Ray actors, K rollout actors feeding the
table, eval actors beside them, and the learner in the driver. Ray is an extra
(the `ray` extra); nothing here imports it until a run asks for it.
"""

from __future__ import annotations

from types import ModuleType

from relayrl.errors import UserError, install


def require_ray() -> ModuleType:
    try:
        import ray
    except ImportError:
        raise UserError("distributed.num_actors > 0 needs Ray, which is not installed; "
                        f"install it with: {install('ray')} (or set distributed.num_actors=0)") from None
    return ray
