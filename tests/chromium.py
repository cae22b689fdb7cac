"""Headless Debian Chromium for the browser tests (live view, watch page, GLB viewer)."""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
from pathlib import Path

import pytest

FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--enable-unsafe-swiftshader")
"""As root, with no GPU and a closed network (no background connections; WebGL through SwiftShader)."""


def run_chromium(args: list[str], profile: Path, timeout_s: float = 120) -> str:
    """Run headless Chromium with a fresh profile folder in its own process group (killed whole if
    it hangs); returns its stdout."""
    process = subprocess.Popen([shutil.which("chromium"), *FLAGS, f"--user-data-dir={profile}", *args],
                               stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, start_new_session=True)
    try:
        out, _ = process.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.communicate()
        pytest.fail(f"headless chromium did not finish in {timeout_s:g} s")
    return out
