"""The model-from-code script of skidbench's MLflow Models (MLflow runs it when it loads one; see
:mod:`skidbench.benchmark.tracking.mlflow_model`): a copy of it is stored with every logged model."""

from mlflow.models import set_model

from skidbench.benchmark.tracking.mlflow_model import SkidbenchModel

set_model(SkidbenchModel())
