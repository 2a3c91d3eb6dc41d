"""skidbench.benchmark: horizon evaluation, MLflow logging, reports, discrepancy discovery, benchmarks."""
