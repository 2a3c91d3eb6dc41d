"""Dynamics models: each window starts from the robot's state (the ``state`` input protocol,
models/rollout.py)."""
