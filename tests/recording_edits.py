"""Copies of a daemon recording (MCAP) with messages edited, dropped or its configuration changed: the damaged and
altered recordings the replay tests feed ``python -m onboard.replay`` and ``groundsim report``; a recording's
top-level records (:func:`top_records`), for the tests that damage them one by one."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

#: an edit of one message's bytes: the new bytes, or None to drop the message
Edit = Callable[[bytes], "bytes | None"]


def rewrite_recording(
    src: Path,
    dst: Path,
    edit_of: Callable[[str, int, str], Edit | None],
    worker: str | None = None,
    compression: str = "none",
    chunked: bool = True,
) -> int:
    """Copy ``src`` to ``dst``, each message through ``edit_of(topic, index on that topic, schema name)`` when that
    gives an edit; ``worker`` sets the metadata's ``estimator.worker``; ``compression`` the chunks' ("none", "lz4",
    "zstd"), ``chunked`` False writes every record outside chunks.  Returns the last edited message's log time (ns),
    or 0."""
    import yaml
    from mcap.records import Channel, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader
    from mcap.writer import CompressionType, Writer

    schema_ids: dict = {}
    schema_names: dict = {}
    channel_ids: dict = {}
    channels: dict = {}  # channel id -> (topic, schema name)
    seen: dict = {}
    edited_log_ns = 0
    with open(src, "rb") as f, open(dst, "wb") as out:
        w = Writer(out, compression=CompressionType[compression.upper()], use_chunking=chunked)
        w.start()
        for rec in StreamReader(f, validate_crcs=False).records:
            if isinstance(rec, Schema) and rec.id not in schema_ids:
                schema_ids[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
                schema_names[rec.id] = rec.name
            elif isinstance(rec, Channel) and rec.id not in channel_ids:
                channel_ids[rec.id] = w.register_channel(
                    rec.topic, rec.message_encoding, schema_ids.get(rec.schema_id, 0), dict(rec.metadata)
                )
                channels[rec.id] = (rec.topic, schema_names.get(rec.schema_id, ""))
            elif isinstance(rec, Message):
                topic, schema = channels[rec.channel_id]
                index = seen.get(topic, 0)
                seen[topic] = index + 1
                data: bytes | None = rec.data
                edit = edit_of(topic, index, schema)
                if edit is not None:
                    data = edit(rec.data)
                    edited_log_ns = rec.log_time
                if data is not None:
                    w.add_message(channel_ids[rec.channel_id], rec.log_time, data, rec.publish_time, rec.sequence)
            elif isinstance(rec, Metadata):
                meta = dict(rec.metadata)
                if rec.name == "irtrack" and worker is not None:
                    raw = yaml.safe_load(meta["config_yaml"])
                    raw.setdefault("estimator", {})["worker"] = worker
                    meta["config_yaml"] = yaml.safe_dump(raw, sort_keys=False)
                w.add_metadata(rec.name, meta)
        w.finish()
    return edited_log_ns


def top_records(data: bytes) -> list[tuple[int, int, int]]:
    """``(byte, opcode, length)`` of each top-level record of an MCAP file's ``data``, from its header to its footer,
    walked by each record's head (in a file cut short: to the last whole head)."""
    import struct

    out = []
    pos = 8  # after the magic
    while pos + 9 <= len(data):
        opcode, length = struct.unpack_from("<BQ", data, pos)
        out.append((pos, opcode, length))
        if opcode == 0x02:  # the footer
            break
        pos += 9 + length
    return out
