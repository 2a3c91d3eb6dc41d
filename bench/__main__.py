"""``python -m bench [names] [--quick]``: run the comparisons (see harness.py)."""

from .harness import main

main()
