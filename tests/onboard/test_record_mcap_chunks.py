"""onboard.io.mcap_chunks: the recorder's zero-copy MCAP writer writes the very bytes the `mcap` package's own
``mcap.writer.Writer`` writes for the same calls (records, chunk boundaries, indexes, summary, CRCs when asked), whatever
the message sizes, channels, times and chunk size (hypothesis), with messages given as one buffer or as pieces; and
the package's reader reads it back."""

from __future__ import annotations

import io
import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.io.mcap_chunks import ChunkWriter

mcap_writer = pytest.importorskip("mcap.writer")
from mcap.reader import make_reader  # noqa: E402

COMPRESSION = {
    "none": mcap_writer.CompressionType.NONE,
    "lz4": mcap_writer.CompressionType.LZ4,
    "zstd": mcap_writer.CompressionType.ZSTD,
}

# one call of the writer's interface: ("schema", name) | ("channel", schema index) | ("message", channel index,
# log time, size, pieces) | ("flush",)
_call = st.one_of(
    st.tuples(st.just("schema"), st.sampled_from(["a", "foxglove.RawImage", "irtrack.track/2"])),
    st.tuples(st.just("channel"), st.integers(0, 3)),
    st.tuples(st.just("message"), st.integers(0, 5), st.integers(0, 2**40), st.integers(0, 70_000), st.integers(1, 3)),
    st.tuples(st.just("flush")),
)


def _drive(w, calls, *, pieces: bool) -> None:
    w.start(profile="", library="test")
    w.add_metadata("irtrack", {"config_yaml": "a: 1\n", "vehicle": "uav1"})
    schemas, channels = [], []
    rng = np.random.default_rng(0)
    for k, call in enumerate(calls):
        if call[0] == "schema":
            schemas.append(w.register_schema(call[1] + str(k), "jsonschema", b'{"type":"object"}'))
        elif call[0] == "channel" and schemas:
            channels.append(w.register_channel(f"/t{k}", "json", schemas[call[1] % len(schemas)], {}))
        elif call[0] == "message" and channels:
            _, ci, t_ns, size, n_pieces = call
            data = rng.integers(0, 256, size, dtype=np.uint8)
            cuts = sorted(rng.integers(0, size + 1, n_pieces - 1))  # drawn either way: the same data follows
            if pieces and n_pieces > 1:
                payload = [memoryview(p) for p in np.split(data, cuts)]
            else:
                payload = data.tobytes()
            w.add_message(channels[ci % len(channels)], t_ns, payload, t_ns + 7, sequence=k)
        elif call[0] == "flush":
            w.flush()
    w.finish()


def _theirs(calls, chunk_size: int, compression: str, crcs: bool) -> bytes:
    buf = io.BytesIO()
    w = mcap_writer.Writer(buf, chunk_size=chunk_size, compression=COMPRESSION[compression], enable_crcs=crcs)
    _drive(w, calls, pieces=False)
    return buf.getvalue()


def _ours(path, calls, chunk_size: int, compression: str, crcs: bool) -> bytes:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        w = ChunkWriter(fd, chunk_size=chunk_size, compression=compression, enable_crcs=crcs)
        _drive(w, calls, pieces=True)
        assert w.position == os.lseek(fd, 0, os.SEEK_CUR)
    finally:
        os.close(fd)
    with open(path, "rb") as f:
        return f.read()


@settings(max_examples=60, deadline=None)
@given(
    calls=st.lists(_call, max_size=40),
    chunk_size=st.sampled_from([1, 1000, 64 * 1024, 1024 * 1024]),
    compression=st.sampled_from(["none", "lz4", "zstd"]),
    crcs=st.booleans(),
)
def test_the_same_bytes_as_the_mcap_packages_writer(tmp_path_factory, calls, chunk_size, compression, crcs):
    path = tmp_path_factory.mktemp("chunks") / "ours.mcap"
    assert _ours(path, calls, chunk_size, compression, crcs) == _theirs(calls, chunk_size, compression, crcs)


def test_pieces_read_back_as_one_message(tmp_path):
    path = tmp_path / "p.mcap"
    px = np.arange(512 * 640, dtype=np.uint16).reshape(512, 640)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    w = ChunkWriter(fd, chunk_size=1024 * 1024)
    w.start()
    sid = w.register_schema("s", "jsonschema", b"{}")
    cid = w.register_channel("/img", "json", sid)
    for i in range(7):
        w.add_message(cid, 1000 + i, [b"head", memoryview(px)], 1000 + i, sequence=i)
    w.finish()
    os.close(fd)
    with open(path, "rb") as f:
        msgs = [m for _s, _c, m in make_reader(f).iter_messages()]
    assert [m.sequence for m in msgs] == list(range(7))
    assert all(m.data == b"head" + px.tobytes() for m in msgs)


@settings(max_examples=40, deadline=None)
@given(
    calls=st.lists(_call, max_size=40),
    chunk_size=st.sampled_from([1, 1000, 64 * 1024]),
    compression=st.sampled_from(["none", "lz4", "zstd"]),
    writer=st.sampled_from(["ours", "theirs"]),
    cut=st.floats(0.0, 1.0),
)
def test_every_file_written_and_every_cut_of_it_passes_the_readers_layout_checks(
    tmp_path_factory, calls, chunk_size, compression, writer, cut
):
    """The structure replay's and record_recover's reader hold a file to (onboard.io.mcap_read) is the one both writers
    write: a finished file reads whole, as the package's indexed reader reads it; one cut at any byte after its magic
    reads as cut, the messages of its whole chunks first."""
    from onboard.io.mcap_read import read_recording

    folder = tmp_path_factory.mktemp("layout")
    path = folder / "f.mcap"
    if writer == "ours":
        data = _ours(path, calls, chunk_size, compression, False)
    else:
        path.write_bytes(data := _theirs(calls, chunk_size, compression, False))
    with open(path, "rb") as f:
        expected = [
            (c.topic, m.log_time, m.sequence, m.data) for _s, c, m in make_reader(f).iter_messages(log_time_order=False)
        ]

    def read(p) -> tuple[list, str | None]:
        msgs, truncated = [], None
        for m in read_recording(str(p)):
            if isinstance(m, dict):
                truncated = m.get("truncated", truncated)
            else:
                msgs.append((m.topic, m.log_time_ns, m.sequence, m.data))
        return msgs, truncated

    assert read(path) == (expected, None)
    size = 8 + int((len(data) - 9) * cut)
    (folder / "cut.mcap").write_bytes(data[:size])
    msgs, truncated = read(folder / "cut.mcap")
    assert msgs == expected[: len(msgs)] and truncated == f"it ends at byte {size}"
