"""Exception types. Each stage raises its own subclass; the CLI prints ``skidbench <stage>: <message>``
as a single line and exits with status 2. Messages name the file and the problem (and the knob to turn)."""

from __future__ import annotations


class SkidbenchError(Exception):
    """Base class of every error that is the user's input, not a bug."""


class ConfigError(SkidbenchError):
    pass


class SimulateError(SkidbenchError):
    pass


class ExtractError(SkidbenchError):
    pass


class GroundTruthError(SkidbenchError):
    pass


class SplitError(SkidbenchError):
    pass


class OutputError(SkidbenchError):
    """An output that cannot be written (disk full, permission, read-only file system)."""


class SourceError(SkidbenchError):
    """A raw source (amrl_txt, drive_df, ...) that cannot be read."""


class ClusterError(SkidbenchError):
    """A sweep that cannot run on its cluster (Ray not installed, the cluster unreachable, a job lost)."""


def one_line(message: str) -> str:
    """Collapse a message to a single line (errors are printed as one line)."""
    return " ".join(str(message).split())
