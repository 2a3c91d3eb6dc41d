"""``skidbench calibrate``: the robot's effective wheel radius and track width, and its wheels' response
to their commands, measured from its own Train data."""
