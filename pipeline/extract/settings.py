"""The ``extract:`` section of the extract stage's config (the keys ``extract.<field>``): how bags are
read and written. The dataclass is the section's schema and defaults (stored in Hydra's ConfigStore,
``pipeline/cli/config_schema.py``; conf/extract.yaml lists it); the stage reads it whole,
``OmegaConf.to_object(cfg.extract)``."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

from skidbench.pipeline.core.errors import ConfigError

#: Images: "ref" keeps the bytes in the bag (index, nbytes), "inline" adds a binary column, "files" writes
#: one file per image under <seq>/images/<key>/.
IMAGE_MODES = ("ref", "inline", "files")
#: The default typestore per bag format (rosbags' ``Stores`` names, lower case): the types of a bag without
#: message definitions, and the types the simulator and the synthetic bags write (``extract.typestores``).
DEFAULT_STORES: Mapping[str, str] = MappingProxyType({"ros1": "ros1_noetic", "ros2": "ros2_humble"})


@dataclass(frozen=True)
class ExtractOptions:
    """``extract.*``: ``images`` (:data:`IMAGE_MODES`), ``batch_rows``: rows buffered per table before a
    Parquet write (bounds memory); ``batch_bytes``: image bytes buffered per table before a write;
    ``force``: re-extract sequences whose _extract.json says they are up to date; ``progress``: tqdm
    progress bars; ``typestores``: the typestore per bag format for bags without message definitions
    (rosbags.typesys.Stores)."""

    images: str = field(default="ref", metadata={"choices": IMAGE_MODES})
    batch_rows: int = field(default=1024, metadata={"lo": 1})
    batch_bytes: int = field(default=8 << 20, metadata={"lo": 1, "what": "bytes"})
    force: bool = False
    progress: bool = True
    typestores: dict[str, str] = field(default_factory=lambda: dict(DEFAULT_STORES))

    def __post_init__(self):
        if self.images not in IMAGE_MODES:
            raise ConfigError(f"extract.images={self.images!r}: must be one of {', '.join(IMAGE_MODES)}")
