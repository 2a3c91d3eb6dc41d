"""Augmented models: a base model plus named physical effects of the discovery catalogue or open-ended
terms: the model side of discrepancy discovery (benchmark/discovery/ searches over them)."""
