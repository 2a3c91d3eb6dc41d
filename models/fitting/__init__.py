"""Fitting a model on a terrain's Train split (``skidbench fit``), and synthetic tables for tests."""
