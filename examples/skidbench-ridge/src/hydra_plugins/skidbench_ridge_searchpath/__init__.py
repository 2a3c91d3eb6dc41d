"""3. Hydra search-path plugin: makes ``pkg://skidbench_ridge.conf`` part of every skidbench config search
path, so ``model=ridge`` resolves to ``skidbench_ridge/conf/model/ridge.yaml`` after ``pip install``.
(``hydra_plugins`` is a namespace package: no ``__init__.py`` in it.)"""

from hydra.core.config_search_path import ConfigSearchPath
from hydra.plugins.search_path_plugin import SearchPathPlugin


class SkidbenchRidgeSearchPathPlugin(SearchPathPlugin):
    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        search_path.append(provider="skidbench-ridge", path="pkg://skidbench_ridge.conf")
