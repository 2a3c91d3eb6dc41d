"""Discrepancy discovery: where a model and the data disagree, the effect it names, the gap it closes."""
