"""Kept for code written against the old private name; import :mod:`skidbench.models.columns`."""

from .columns import TARGETS, col, mse, sequence_starts, targets, training_rows

__all__ = ["TARGETS", "col", "mse", "sequence_starts", "targets", "training_rows"]
