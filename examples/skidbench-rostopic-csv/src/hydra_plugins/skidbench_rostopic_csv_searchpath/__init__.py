"""3. Hydra search-path plugin: makes ``pkg://skidbench_rostopic_csv.conf`` part of every skidbench config
search path, so ``source=rostopic_csv`` resolves to ``skidbench_rostopic_csv/conf/source/rostopic_csv.yaml``
after ``pip install``. (``hydra_plugins`` is a namespace package: no ``__init__.py`` in it.)"""

from hydra.core.config_search_path import ConfigSearchPath
from hydra.plugins.search_path_plugin import SearchPathPlugin


class SkidbenchRostopicCsvSearchPathPlugin(SearchPathPlugin):
    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        search_path.append(provider="skidbench-rostopic-csv", path="pkg://skidbench_rostopic_csv.conf")
