"""The benchmark's maths, pure: the horizon error, the metrics, intervals, the floor and the standings.
Nothing here opens a file or talks to MLflow (tests/test_layers.py checks it)."""
