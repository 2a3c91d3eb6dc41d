"""skidbench.pipeline: the staged data pipeline (simulate -> extract -> groundtruth -> splits).

Pure computation lives in modules that take arrays and tables; each stage has a thin Hydra entry
point (``*_app.py`` / ``app.py``) that does the I/O.

Importing it caps the numerical libraries' processor code paths at one level (``cpu.pin``: same inputs,
same bytes on every machine of the benchmark's kind); it must run before NumPy loads, so the other
subpackages import this one first.
"""

from skidbench.pipeline.runner.cpu import pin as _pin_code_paths

_pin_code_paths()

__version__ = "0.1.0"
