"""Networks, each defined once: the MLP and twin MLP (mlp.py) with one activation registry
(activations.py), the observation encoders chosen from the observation space (encoders.py)
(the Nature CNN among them), and the MLPs' fast twins (mlp_fast.py): an inference path for
actors and hand-written gradients for learners."""

from relayrl.nn.activations import ACTIVATIONS, Activation
from relayrl.nn.mlp import MLP, TwinMLP, tf_agents_init_

__all__ = ["ACTIVATIONS", "MLP", "Activation", "TwinMLP", "tf_agents_init_"]
