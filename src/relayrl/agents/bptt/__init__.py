"""BPTT: a policy trained by backpropagating the reward through stateless-env rollouts."""
