"""The linter as a test: ruff with the rules in ruff.toml (import sorting and unused names among them)."""

import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_ruff_finds_nothing():
    ruff = Path(sys.executable).parent / 'ruff'
    command = [str(ruff)] if ruff.exists() else [shutil.which('ruff') or 'ruff']
    result = subprocess.run([*command, 'check', '--no-cache', '--output-format', 'concise', '.'], cwd=REPO,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
