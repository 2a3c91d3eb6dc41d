"""The checks beside the effect search, whose answers are never a robot effect: the ground truth's own
consistency (``ground_truth``: a heading, scale or clock problem reported as such), the speed scale as a
calibration finding (``scale``) and the placebo on commands that did not drive the motion (``placebo``)."""
