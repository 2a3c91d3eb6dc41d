"""The closed-form kinematic models of the paper: ideal, extended differential drive, full linear,
ROC-based, enhanced kinematic."""
