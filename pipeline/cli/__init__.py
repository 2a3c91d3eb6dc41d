"""The command line: ``skidbench <stage> [overrides]``, the overrides checked before a stage runs, and the
in-process entry points."""
