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
#: headless, as root in a container too (no sandbox; /dev/shm there is often 64 MB, too small for a page:
#: shared memory in /tmp instead), nothing fetched but the page
FLAGS = (
    "--headless", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu", "--disable-quic",
    "--no-first-run", "--disable-background-networking", "--disable-component-update", "--disable-sync",
)  # fmt: skip


def run_chromium(
    url: str,
    tmp: Path,
    *,
    screenshot: Path | None = None,
    budget_ms: int = 20000,
    console: bool = False,
    window: str = "1600,1000",
) -> subprocess.CompletedProcess:  # noqa: E501 fmt: skip
    """Chromium on ``url`` for ``budget_ms`` of (virtual) time in a ``window`` (width,height) of a fresh
    profile: the DOM on stdout (or a screenshot); with ``console``, the page's console messages on stderr
    (``CONSOLE(<line>)`` lines)."""
    profile = tmp / f"profile-{len(list(tmp.glob('profile-*')))}"
    args = [CHROMIUM, *FLAGS, f"--user-data-dir={profile}", f"--window-size={window}",
            f"--virtual-time-budget={budget_ms}"]  # fmt: skip
    if console:
        args += ["--enable-logging=stderr", "--v=0"]
    args += [f"--screenshot={screenshot}"] if screenshot else ["--dump-dom"]
    done = subprocess.run([*args, url], capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, done.stderr[-2000:]
    return done


def chromium(url: str, tmp: Path, *, screenshot: Path | None = None, budget_ms: int = 20000,
             window: str = "1600,1000") -> str:  # fmt: skip
    """The DOM of ``url`` after the page has run ``budget_ms`` of (virtual) time; or save a screenshot."""
    return run_chromium(url, tmp, screenshot=screenshot, budget_ms=budget_ms, window=window).stdout


def console_messages(stderr: str) -> list[str]:
    """The page's console messages (and uncaught errors) among Chromium's log lines."""
    return [ln for ln in stderr.splitlines() if "CONSOLE" in ln or "Uncaught" in ln]


def text_of(dom: str) -> str:
    dom = re.sub(r"<(script|style)\b.*?</\1>", " ", dom, flags=re.S)
    return re.sub(r"\s+", " ", html.unescape(re.sub(r"<[^>]+>", " ", dom)))


def page_value(url: str, tmp: Path, expression: str, *, window: str = "1920,1080", timeout_s: float = 150.0):
    """Open ``url`` in headless Chromium (a fresh profile, the flags above) and return the value of the
    JavaScript ``expression`` (JSON-able) as soon as it is truthy: what the page computes once rendered
    (element positions, say). Spoken over Chromium's DevTools pipe (fds 3 and 4); AssertionError at the
    timeout, with the last value."""
    import json
    import os
    import time

    profile = tmp / f"profile-{len(list(tmp.glob('profile-*')))}"
    to_chrome, from_chrome = os.pipe(), os.pipe()

    def fds():  # Chromium reads commands from fd 3 and writes answers to fd 4
        import fcntl

        high = [fcntl.fcntl(fd, fcntl.F_DUPFD, 10) for fd in (to_chrome[0], from_chrome[1])]  # not 3 or 4
        os.dup2(high[0], 3)
        os.dup2(high[1], 4)

    args = [CHROMIUM, *FLAGS, f"--user-data-dir={profile}", f"--window-size={window}",
            "--remote-debugging-pipe", "about:blank"]  # fmt: skip
    proc = subprocess.Popen(args, preexec_fn=fds, pass_fds=(3, 4), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)  # fmt: skip
    os.close(to_chrome[0])
    os.close(from_chrome[1])
    buf, n = b"", 0

    def send(method: str, params: dict, session: str | None = None) -> dict:
        nonlocal buf, n
        n += 1
        msg = {"id": n, "method": method, "params": params, **({"sessionId": session} if session else {})}
        os.write(to_chrome[1], json.dumps(msg).encode() + b"\0")
        while True:
            while b"\0" not in buf:
                chunk = os.read(from_chrome[0], 1 << 16)
                assert chunk, "chromium closed its DevTools pipe"
                buf += chunk
            raw, buf = buf.split(b"\0", 1)
            msg = json.loads(raw)
            if msg.get("id") == n:
                assert "error" not in msg, msg["error"]
                return msg["result"]

    try:
        target = send("Target.createTarget", {"url": "about:blank"})["targetId"]
        session = send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        send("Page.navigate", {"url": url}, session)
        deadline, value = time.monotonic() + timeout_s, None
        while time.monotonic() < deadline:
            value = send("Runtime.evaluate", {"expression": expression, "returnByValue": True}, session)
            value = value["result"].get("value")
            if value:
                return value
            time.sleep(0.5)
        raise AssertionError(f"{url}: {expression[:80]}... still {value!r} after {timeout_s:g} s")
    finally:
        proc.kill()
        proc.wait()
        os.close(to_chrome[1])
        os.close(from_chrome[0])
