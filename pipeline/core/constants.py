"""Physical constants the package shares (one home: import them, never rewrite them).

``STANDARD_GRAVITY`` is the standard acceleration of gravity, 9.80665 m/s^2 exactly (3rd CGPM, 1901; the
value of ``scipy.constants.g``). It is the models' g, whatever world their data come from: the friction
model's normal loads and force scale (``models/friction/balance.py``) and the enhanced model's
gravitational forces (``models/kinematic/enhanced.py``).

A simulated world's gravity is a property of that world, not this constant: the built-in simulator's is
``WORLD_GRAVITY`` in ``pipeline/simulate/physics.py`` (9.81 m/s^2), and every simulated dataset was made
with it. The 0.03 % difference is like a real site's local gravity (9.78-9.83 m/s^2) and costs a model
nothing: every ground force of the friction model (eqs. 5-7) is a fitted coefficient times the normal
load, and on flat ground the enhanced model's force ratios (centrifugal force over M g) enter through
fitted coefficients linearly, so the fitted coefficients absorb the ratio exactly.
"""

STANDARD_GRAVITY = 9.80665  # m/s^2
