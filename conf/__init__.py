"""skidbench's Hydra configs. Importing the package (as Hydra does to read them) stores the settings
dataclasses that are the schema of config sections in Hydra's ConfigStore (``schema/<section>``, listed
in ``pipeline/cli/config_schema.py``), so every composition finds them."""

from skidbench.pipeline.cli.config_schema import register_configs

register_configs()
