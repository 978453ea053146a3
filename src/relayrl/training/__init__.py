"""The Actor–Learner loop, triggers, evaluation, checkpoints and the run directory."""
