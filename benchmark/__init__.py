"""skidbench.benchmark: horizon evaluation, MLflow logging, reports, discrepancy discovery, benchmarks."""

import skidbench.pipeline  # noqa: F401 - first: pins the processor code paths before NumPy loads
