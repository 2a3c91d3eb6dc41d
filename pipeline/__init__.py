"""skidbench.pipeline: the staged data pipeline (simulate -> extract -> groundtruth -> splits).

Pure computation lives in modules that take arrays and tables; each stage has a thin Hydra entry
point (``*_app.py`` / ``app.py``) that does the I/O.
"""

__version__ = "0.1.0"
