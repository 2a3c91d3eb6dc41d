"""The config sections of the release stages: publish's ``publish:`` (:class:`PublishOptions`), score's
``score:`` (:class:`ScoreOptions`) and the ``bundle:`` section, whose keys differ between export
(:class:`ExportBundle`) and import (:class:`ImportBundle`). Each dataclass is its section's schema and
defaults (stored in Hydra's ConfigStore, ``pipeline/cli/config_schema.py``); the app reads a section
whole, ``OmegaConf.to_object(cfg.publish)``. Imports nothing heavy (the schema is registered before every
composition)."""

from __future__ import annotations

from dataclasses import dataclass, field

#: a bundle's releases (``bundle.release``): ``withheld`` (a public half without the CV/LD ground truth,
#: and a private half with it) or ``open`` (one bundle with everything)
RELEASES = ("withheld", "open")


@dataclass(frozen=True)
class PublishOptions:
    """The ``publish`` section: the site folder (``<dir>/<dataset>/index.html``, and ``<dir>/index.html``
    listing every dataset in it: the second argument), whether the page has figures (compare's report, and
    Figs. 3/4 per protocol, as inline PNG images) and their resolution, the page's title (None: the dataset
    card's: robot, terrains, source) and where readers get the public half (a URL; None: the page says to
    ask the maintainer)."""

    dir: str = "???"
    figures: bool = True
    dpi: int = field(default=72, metadata={"lo": 20, "hi": 600})
    title: str | None = None
    download: str | None = None


@dataclass(frozen=True)
class ScoreOptions:
    """The ``score`` section: the predictions file (.parquet or .csv: ``--predictions <file>``), the
    method's name on the board (None: the file's name without its suffixes), a link to its paper or code
    (http(s)://... or doi:10....) and who submits it (both required to score), the submission's date
    (YYYY-MM-DD; None: today, UTC), one line on the method, and ``check`` (true: check the file's shape
    only, score nothing)."""

    predictions: str = "???"
    name: str | None = None
    link: str | None = None
    submitter: str | None = None
    date: str | None = None
    description: str | None = None
    check: bool = False


@dataclass(frozen=True)
class ExportBundle:
    """Export's ``bundle`` section: the bundle folder to write (new or empty: the second argument), the
    release (:data:`RELEASES`; ``open``: one bundle, test truth included, for public data), the licence of
    the source data (an SPDX id or the terms; None: only for simulated data) and where the data come from
    (a URL, a DOI, a sentence; None: from dataset.json)."""

    dir: str = "???"
    release: str = field(default="withheld", metadata={"choices": RELEASES})
    licence: str | None = None
    provenance: str | None = None


@dataclass(frozen=True)
class ImportBundle:
    """Import's ``bundle`` section: the bundle folder (the argument), the dataset's name under out_root
    (None: the exported dataset's) and the private half (``<dir>/private`` of export: the CV/LD answers, to
    score; None: without them)."""

    dir: str = "???"
    name: str | None = None
    answers: str | None = None
