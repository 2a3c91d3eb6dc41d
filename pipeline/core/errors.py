"""Exception types. Each stage raises its own subclass; the CLI prints ``skidbench <stage>: <message>``
as a single line and exits with status 2. Messages name the file and the problem (and the knob to turn).

Exit statuses of ``skidbench <stage>`` (pipeline/cli/main.py): 0 done; 2 bad input or a failed stage (one line
``error: ...``); 3 the stage ran to its end but some of its runs failed (:class:`PartialFailure`: ``evaluate``
when a model's run FAILED; each failure is recorded with its traceback, the other runs are valid and
``compare`` uses them); 130 interrupted (Ctrl-C: one line, no traceback).
"""

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


EXIT_ERROR = 2
EXIT_PARTIAL = 3
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as a shell reports an interrupted command


class PartialFailure(Exception):  # noqa: N818 (not an error of the input: the stage ran to its end)
    """A stage that ran to its end but some of its units failed, each recorded where it belongs (a FAILED
    MLflow run with its reason and traceback): the CLI prints the message (the summary) on stderr and exits
    with :data:`EXIT_PARTIAL`; the stage is not marked failed, so the stages after it use what succeeded."""


def one_line(message: str) -> str:
    """Collapse a message to a single line (errors are printed as one line)."""
    return " ".join(str(message).split())
