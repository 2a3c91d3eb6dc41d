"""Fault injection for the reliability tests, kept out of the installed package.

``SKIDBENCH_FAULT=<action>@<n>[:<substring>]`` acts at the n-th atomic write (1-based) of this process
whose final path contains ``substring``, after the temporary file is written and before it is renamed:
``kill`` sends SIGKILL to the process group (a killed run; start it in a session of its own); ``int``
sends SIGINT to the process (Ctrl-C: Python raises KeyboardInterrupt there); ``stop`` sends SIGSTOP to the
process (it waits there until the test sends SIGCONT: something happens mid-run);
``enospc`` / ``eacces`` raise that OSError (a full disk / a permission error), which
``skidbench.pipeline.core.io.atomic_path`` then handles as it would a real one.

:func:`install` replaces ``skidbench.pipeline.core.io.atomic_path`` by a wrapper before any stage module
imports it (sitecustomize.py in this folder calls it at start-up), so every write of every stage goes
through the hook, the writes inside ``skidbench.pipeline.core.io`` included.
"""

from __future__ import annotations

import contextlib
import errno
import os
import signal
from pathlib import Path

FAULT_ENV = "SKIDBENCH_FAULT"
_count = [0]


def inject(final: Path, spec: str | None = None) -> None:
    """Act on ``final`` if it is the write ``spec`` (default: ``$SKIDBENCH_FAULT``) names."""
    spec = os.environ.get(FAULT_ENV) if spec is None else spec
    if not spec:
        return
    action, _, rest = spec.partition("@")
    nth, _, needle = rest.partition(":")
    if needle and needle not in str(final):
        return
    _count[0] += 1
    if _count[0] != int(nth or 1):
        return
    if action == "kill":  # the whole process group: a stage and its worker processes die together
        os.killpg(os.getpgid(0), signal.SIGKILL)
    if action == "stop":  # frozen until SIGCONT
        os.kill(os.getpid(), signal.SIGSTOP)
    if action == "int":  # Ctrl-C: the handler raises KeyboardInterrupt before the next bytecode
        if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
            # started from a shell's background job (`make test &` in a script), which ignores SIGINT and
            # so hands its children an ignored Ctrl-C: a terminal's Ctrl-C reaches a foreground stage
            signal.signal(signal.SIGINT, signal.default_int_handler)
        os.kill(os.getpid(), signal.SIGINT)
    code = {"enospc": errno.ENOSPC, "eacces": errno.EACCES}.get(action)
    if code is not None:
        raise OSError(code, os.strerror(code), str(final))


def install() -> None:
    """Wrap ``skidbench.pipeline.core.io.atomic_path`` so :func:`inject` runs between a write and its
    rename."""
    from skidbench.pipeline.core import io

    original = io.atomic_path
    if getattr(original, "_fault_hook", False):
        return

    @contextlib.contextmanager
    def atomic_path(final, suffix: str = ""):
        with original(final, suffix) as tmp:
            yield tmp
            inject(Path(final))  # inside the original's block: its error handling and clean-up apply

    atomic_path.__doc__ = original.__doc__
    atomic_path._fault_hook = True
    io.atomic_path = atomic_path
