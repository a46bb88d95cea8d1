"""The daemon's threads carry their names into the OS (what top -H, ps -L and the bench read)."""

import sys
import threading

import pytest

from onboard.app.os_thread import name_os_thread


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc and prctl are Linux's")
def test_a_named_thread_shows_its_name_in_proc_cut_to_15_bytes():
    seen = {}

    def body():
        seen["ok"] = name_os_thread("irtrack-pipeline-thread")
        with open(f"/proc/self/task/{threading.get_native_id()}/comm") as f:
            seen["comm"] = f.read().strip()

    t = threading.Thread(target=body)
    t.start()
    t.join(5)
    assert seen == {"ok": True, "comm": "irtrack-pipelin"}
    with open(f"/proc/self/task/{threading.get_native_id()}/comm") as f:
        assert f.read().strip() != "irtrack-pipelin"  # the caller's thread only
