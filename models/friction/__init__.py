"""The friction-based kinematic model (the paper's section III): its force balance, solver and fit."""
