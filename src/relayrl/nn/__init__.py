"""Networks, each defined once: the MLP and twin MLP (mlp.py) with one activation registry
(activations.py), the observation encoders chosen from the observation space (encoders.py),
the conv Q-network (conv.py), and the MLPs' fast twins (mlp_fast.py): an inference path for
actors and hand-written gradients for learners."""

from relayrl.nn.activations import ACTIVATIONS, Activation
from relayrl.nn.conv import CONV_NETWORKS, NATURE_CONVS, NATURE_HIDDEN, ConvQNet
from relayrl.nn.mlp import MLP, TwinMLP, tf_agents_init_

__all__ = ["ACTIVATIONS", "CONV_NETWORKS", "MLP", "NATURE_CONVS", "NATURE_HIDDEN", "Activation", "ConvQNet",
           "TwinMLP", "tf_agents_init_"]
