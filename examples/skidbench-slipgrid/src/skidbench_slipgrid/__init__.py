"""Example learned skidbench model plugin (skidbench's docs/plugins.md)."""

from .model import SlipGrid

__all__ = ["SlipGrid"]
