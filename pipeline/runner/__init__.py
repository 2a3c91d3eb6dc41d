"""How stages run: forked local workers, commands side by side, Ray tasks on a cluster, the processor
code paths pinned, and the code and environment every result records."""
