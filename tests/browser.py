"""Headless Chromium for the browser tests (the MLflow UI: tests/test_mlflow_ui_browser.py; the published
benchmark page: tests/test_release.py): where it is, and a page's DOM after it ran, with the console."""

from __future__ import annotations

import html
import re
import shutil
import subprocess
from pathlib import Path

#: Debian's chromium (`make test` installs it where it can: the Makefile); None: the browser tests skip
CHROMIUM = next((p for p in (shutil.which("chromium"), "/usr/bin/chromium") if p and Path(p).is_file()), None)


def run_chromium(url: str, tmp: Path, *, screenshot: Path | None = None, budget_ms: int = 20000,
                 console: bool = False) -> subprocess.CompletedProcess:  # fmt: skip
    """Chromium on ``url`` for ``budget_ms`` of (virtual) time: the DOM on stdout (or a screenshot); with
    ``console``, the page's console messages on stderr (``CONSOLE(<line>)`` lines)."""
    profile = tmp / f"profile-{len(list(tmp.glob('profile-*')))}"
    args = [
        CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync",
        f"--user-data-dir={profile}", "--window-size=1600,1000", f"--virtual-time-budget={budget_ms}",
    ]  # fmt: skip
    if console:
        args += ["--enable-logging=stderr", "--v=0"]
    args += [f"--screenshot={screenshot}"] if screenshot else ["--dump-dom"]
    done = subprocess.run([*args, url], capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, done.stderr[-2000:]
    return done


def chromium(url: str, tmp: Path, *, screenshot: Path | None = None, budget_ms: int = 20000) -> str:
    """The DOM of ``url`` after the page has run ``budget_ms`` of (virtual) time; or save a screenshot."""
    return run_chromium(url, tmp, screenshot=screenshot, budget_ms=budget_ms).stdout


def console_messages(stderr: str) -> list[str]:
    """The page's console messages (and uncaught errors) among Chromium's log lines."""
    return [ln for ln in stderr.splitlines() if "CONSOLE" in ln or "Uncaught" in ln]


def text_of(dom: str) -> str:
    dom = re.sub(r"<(script|style)\b.*?</\1>", " ", dom, flags=re.S)
    return re.sub(r"\s+", " ", html.unescape(re.sub(r"<[^>]+>", " ", dom)))
