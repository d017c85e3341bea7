"""Waiting for a ``bb-align serve`` child process (the bench and soak harnesses start one) to be ready."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path
from typing import Callable


def log_tail(path: Path, n: int = 800) -> str:
    try:
        return path.read_text(errors="replace")[-n:]
    except OSError:
        return "(no log)"


def wait_until_ready(proc: subprocess.Popen, rest_url: str, timeout_s: float, log_path: Path,
                     stop: Callable[[], object]) -> None:
    """Poll ``rest_url``/readyz until it answers 200. RuntimeError (with the log's tail) when the process exits
    first, or, after calling ``stop``, when ``timeout_s`` passes."""
    import httpx

    deadline = time.monotonic() + timeout_s
    while True:
        if proc.poll() is not None:
            raise RuntimeError(f"the service exited with code {proc.returncode}: {log_tail(log_path)}")
        try:
            if httpx.get(rest_url + "/readyz", timeout=2).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        if time.monotonic() > deadline:
            stop()
            raise RuntimeError(f"the service was not ready within {timeout_s} s: {log_tail(log_path)}")
        time.sleep(0.2)
