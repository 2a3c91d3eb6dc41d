"""Hydra search-path plugin: ``model=slipgrid`` finds ``skidbench_slipgrid/conf/model/slipgrid.yaml``."""

from hydra.core.config_search_path import ConfigSearchPath
from hydra.plugins.search_path_plugin import SearchPathPlugin


class SkidbenchSlipgridSearchPathPlugin(SearchPathPlugin):
    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        search_path.append(provider="skidbench-slipgrid", path="pkg://skidbench_slipgrid.conf")
