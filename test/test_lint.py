"""Lint and types are tests: ``ruff check`` (ruff.toml) on the whole tree and ``mypy`` (mypy.ini:
strict on the core) must pass."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(args: list[str]) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", *args], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=280)


def test_ruff():
    r = _run(["ruff", "check", "--no-cache", "."])
    assert r.returncode == 0, r.stdout + r.stderr


@pytest.mark.timeout(300)
def test_mypy_strict_on_the_core():
    r = _run(["mypy", "--config-file", "mypy.ini", "--cache-dir", str(ROOT / ".mypy_cache")])
    assert r.returncode == 0, r.stdout + r.stderr
    assert "Success" in r.stdout
