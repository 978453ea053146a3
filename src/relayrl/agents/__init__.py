"""Agents: one folder per algorithm with config, pure losses, networks and the agent; the
registry (agents/registry.py) says what each algorithm is."""
