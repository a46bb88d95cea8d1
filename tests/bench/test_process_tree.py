"""children_by_parent: the /proc parent map that ProcCpu, bench.companion and bench.soak walk the daemon's tree with."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from bench.soak import process_tree
from groundsim.evaluation.proc_cpu import children_by_parent

pytestmark = pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="reads /proc (Linux)")


def test_a_child_and_its_child_are_found_under_their_parents():
    # a child that starts a grandchild, then waits on stdin: both alive while the map is read
    code = "import subprocess, sys; g = subprocess.Popen([sys.executable, '-c', 'input()'], stdin=sys.stdin); "
    code += "print(g.pid, flush=True); g.wait()"
    child = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout is not None
        grandchild = int(child.stdout.readline())
        kids = children_by_parent()
        assert child.pid in kids[os.getpid()]
        assert kids[child.pid] == [grandchild]
        assert [pid for pid, _kind in process_tree(child.pid)] == [child.pid, grandchild]
    finally:
        child.communicate("\n", timeout=10)
