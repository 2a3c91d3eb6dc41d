"""``python -m perf [names] [--quick]``: run the comparisons (see harness.py)."""

from .harness import main

main()
