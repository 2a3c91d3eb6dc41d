"""skidbench's Hydra launcher for Ray (``hydra/launcher=ray``); the work is in
:mod:`skidbench.pipeline.runner.cluster`. Hydra finds launchers in the ``hydra_plugins`` namespace package (no
``__init__.py`` in ``hydra_plugins/`` itself). This module must not import Ray: Hydra imports every plugin
at start-up, and Ray is optional."""
