"""Properties of onboard.io.record_files (hypothesis): the names of a rotated recording and the name a new one takes.

* :func:`rotation_base` inverts :func:`rotated_path` for every index and every ``record.path`` (a name ending in
  ``.mcap``, as the config requires), and what it names rotates back to the path it was given;
* a recording's files have distinct names;
* :func:`free_recording_path`, whatever flights a folder holds, returns the path when it and its rotated files are
  free, else a name ending in ``.mcap`` none of whose rotated files exists: it writes over no earlier flight;
* :func:`rotated_paths_after` lists exactly the recording's existing files after an index, in order, up to a gap.
"""

from __future__ import annotations

import os
import tempfile

from hypothesis import example, given, settings
from hypothesis import strategies as st

from onboard.io.record_files import free_recording_path, rotated_path, rotated_paths_after, rotation_base

# file names as a config or an operator writes them: dots, digits, dashes, glob's metacharacters, spaces, unicode
name_chars = st.sampled_from(list("ab1.-_[]*? é"))
stems = st.text(name_chars, max_size=8)
record_paths = st.builds(lambda d, s: f"{d}{s}.mcap", st.sampled_from(["", "/tmp/x/", "rec/", "./"]), stems)
indices = st.integers(0, 10**6)


@settings(max_examples=200, deadline=None)
@given(record_paths, indices)
@example(".mcap", 1)  # a recording named .mcap: its part .1.mcap named no base
@example("a.1.mcap", 0)
def test_rotation_base_inverts_rotated_path(path, index):
    assert rotation_base(rotated_path(path, index), index) == path


@settings(max_examples=200, deadline=None)
@given(st.one_of(record_paths, st.text(name_chars, max_size=14)), indices)
def test_what_rotation_base_names_rotates_back_to_the_path(path, index):
    base = rotation_base(path, index)
    if base is not None:
        assert rotated_path(base, index) == path


@settings(max_examples=100, deadline=None)
@given(record_paths, st.sets(indices, min_size=2, max_size=6))
def test_a_recordings_files_have_distinct_names(path, index_set):
    names = [rotated_path(path, i) for i in index_set]
    assert len(set(names)) == len(names) and all(n.endswith(".mcap") for n in names)


@settings(max_examples=60, deadline=None)
@given(
    stem=st.text(name_chars.filter(lambda c: c not in "/"), min_size=1, max_size=5),
    existing=st.lists(
        st.tuples(st.sampled_from(["", "-1", "-2", "-3", ".1", "-1.1"]), st.integers(0, 3)), max_size=8, unique=True
    ),
)
@example(stem="a", existing=[("", 2)])  # only a later part of the earlier flight is left
@example(stem="[a]", existing=[("", 1)])  # a glob metacharacter in the name
def test_a_new_recording_writes_over_no_earlier_flight(stem, existing):
    with tempfile.TemporaryDirectory(prefix="irtrack-rec-") as folder:
        path = os.path.join(folder, f"{stem}.mcap")
        files = set()
        for suffix, index in existing:
            f = rotated_path(os.path.join(folder, f"{stem}{suffix}.mcap"), index)
            with open(f, "wb"):
                pass
            files.add(f)
        free = free_recording_path(path)
        assert free.endswith(".mcap") and os.path.dirname(free) == folder
        mine = {rotated_path(free, i) for i in range(8)}
        assert not mine & files, (free, sorted(mine & files))
        # free already: kept as configured.  (A name that only looks like a part, FILE.1.1.mcap of a recording
        # named FILE.1.mcap, also moves it aside: on the safe side.)
        looks_taken = any(
            f == path or (f.startswith(path[: -len(".mcap")] + ".") and f[len(path) - 4 : len(path) - 3].isdigit())
            for f in files
        )
        if not looks_taken:
            assert free == path
        # a recording that rotates writes FILE.N.mcap for N = 1, 2, ...: none of those exist
        assert rotated_paths_after(free, 0) == []


@settings(max_examples=60, deadline=None)
@given(present=st.sets(st.integers(0, 6)), index=st.integers(0, 6))
def test_the_files_after_an_index_are_those_present_up_to_the_first_gap(present, index):
    with tempfile.TemporaryDirectory(prefix="irtrack-rec-") as folder:
        base = os.path.join(folder, "flight.mcap")
        for i in present:
            with open(rotated_path(base, i), "wb"):
                pass
        after = rotated_paths_after(base, index)
        n = 0
        while index + 1 + n in present:
            n += 1
        assert after == [rotated_path(base, index + 1 + k) for k in range(n)]
