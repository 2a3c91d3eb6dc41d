"""Example skidbench model plugin (see the README section "Writing a model plugin")."""

from .model import RidgeSlip

__all__ = ["RidgeSlip"]
