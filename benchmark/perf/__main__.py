"""``python -m skidbench.benchmark.perf [names] [--quick]``: run the comparisons (see harness.py)."""

from .harness import main

main()
