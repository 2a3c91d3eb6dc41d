"""The dataset manifest: which raw recordings exist, and the terrain and category of each.

``<out_root>/<dataset>/raw/manifest.json`` (written by ``simulate``; for a user's bags the ``bag``
source builds the same structure from a directory ``<root>/<terrain>/<category>/*.bag`` or from a
``manifest.json`` the user writes)::

    {"schema": 1, "robot": "jackal", "format": "ros1",
     "sequences": [{"name": "tile_train_00", "terrain": "tile", "category": "train",
                    "path": "bags/tile_train_00.bag"}, ...]}

``category`` is one of ``train``, ``cv``, ``ld`` (the paper's Table I) or ``loop`` (loop-closure
trials). ``path`` is relative to the manifest's folder.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

from skidbench.pipeline.core.errors import ConfigError
from skidbench.pipeline.core.io import write_json_atomic

CATEGORIES = ("train", "cv", "ld", "loop")
SPLITS = ("train", "cv", "ld")
MANIFEST_SCHEMA = 1


@dataclass(frozen=True)
class Sequence:
    name: str
    terrain: str
    category: str
    path: str  # relative to the manifest folder

    def __post_init__(self):
        if self.category not in CATEGORIES:
            raise ConfigError(f"sequence {self.name}: category {self.category!r} is not one of {CATEGORIES}")


@dataclass
class Manifest:
    sequences: list[Sequence]
    robot: str = "jackal"
    format: str = "ros1"
    base: Path = Path(".")

    def resolve(self, seq: Sequence) -> Path:
        return (self.base / seq.path).resolve()

    def by_category(self, category: str) -> list[Sequence]:
        return [s for s in self.sequences if s.category == category]

    @property
    def terrains(self) -> list[str]:
        return sorted({s.terrain for s in self.sequences})

    def write(self, path: Path) -> None:
        write_json_atomic(
            path,
            {
                "schema": MANIFEST_SCHEMA,
                "robot": self.robot,
                "format": self.format,
                "sequences": [asdict(s) for s in self.sequences],
            },
        )

    @classmethod
    def read(cls, path: Path) -> Manifest:
        path = Path(path)
        try:
            data = json.loads(path.read_text())
            seqs = [Sequence(**s) for s in data["sequences"]]
        except FileNotFoundError as exc:
            raise ConfigError(
                f"{path}: no manifest yet: run the stage that writes it first (`skidbench extract` with the "
                "same source settings for your own data; `skidbench simulate` for the simulated dataset)"
            ) from exc
        except (json.JSONDecodeError, KeyError, TypeError) as exc:
            raise ConfigError(f"{path}: not a valid manifest ({exc})") from exc
        return cls(seqs, data.get("robot", "jackal"), data.get("format", "ros1"), path.parent)
