"""Run at interpreter start-up when this folder is on PYTHONPATH (tests/reliability_data.py puts it there
for a run given ``SKIDBENCH_FAULT``): installs the fault hook of :mod:`skidbench_faults` in this process
and, through the inherited environment, in every worker process it starts."""

import os

if os.environ.get("SKIDBENCH_FAULT"):
    import skidbench_faults

    skidbench_faults.install()
