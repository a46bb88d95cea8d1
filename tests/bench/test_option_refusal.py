"""The benchmarks without options of their own refuse an unknown one by name instead of starting their default
run (which takes minutes) as if it had not been given; ``--help`` lists what they take."""

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("name", ["flight", "render", "imaging"])
def test_unknown_option_is_refused_by_name(name):
    proc = subprocess.run(
        [sys.executable, "-m", f"bench.{name}", "--scenes", "C1"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "unrecognized arguments: --scenes C1" in proc.stderr
    assert proc.stdout == ""  # nothing of the default run started


def test_help_lists_the_flags():
    proc = subprocess.run(
        [sys.executable, "-m", "bench.render", "--help"], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    assert "--reference-scenes" in proc.stdout and "--stages" in proc.stdout
