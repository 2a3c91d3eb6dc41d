"""Learned baselines from the literature: DRIVE's Bayesian slip regression and a GP residual model."""
