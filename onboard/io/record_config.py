"""The flight recording's settings: the ``record`` section of the daemon's configuration (composed by
:class:`onboard.app.config.OnboardConfig`; ``groundsim run --record`` builds one from its options), read by
:class:`onboard.io.record.FlightRecorder`.  Apart from the recorder: a configuration reads these limits without the
MCAP writer, its thread and its encoders (:mod:`onboard.io.record` re-exports :class:`RecordConfig`)."""

from __future__ import annotations

import functools
from typing import Annotated, Literal

from onboard.core.schema import Bool, Integer, Number, Text, config_dataclass

__all__ = ["MB", "RecordConfig"]

MB = 1_000_000


@config_dataclass
class RecordConfig:
    """``record``: the flight recording, an MCAP file of the daemon's inputs and outputs (the daemon's
    section, composed by :class:`onboard.app.config.OnboardConfig`; groundsim builds one from its options).
    Sizes in the file's units (MB, KB); :class:`FlightRecorder` reads them in bytes (``*_bytes``)."""

    path: Annotated[str | None, Text(pattern=r"^.*\.mcap$", what="a file name ending in .mcap")] = None
    frames: Bool = True
    max_file_mb: Annotated[float, Number(1.0, 1_000_000.0)] = 2000.0
    max_file_s: Annotated[float, Number(1.0, 86_400.0)] = 600.0
    max_files: Annotated[int, Integer(0, 100_000)] = 0
    chunk_kb: Annotated[int, Integer(16, 65_536)] = 1024
    flush_interval_s: Annotated[float, Number(0.05, 60.0)] = 1.0
    compression: Annotated[Literal["none", "lz4", "zstd"], Text()] = "none"
    queue_mb: Annotated[float, Number(1.0, 4096.0)] = 64.0
    sync_mb: Annotated[float, Number(0.0, 4096.0)] = 8.0
    min_free_mb: Annotated[float, Number(0.0, 1_000_000.0)] = 200.0

    @functools.cached_property
    def max_file_bytes(self) -> int:
        return int(self.max_file_mb * MB)

    @functools.cached_property
    def chunk_bytes(self) -> int:
        return self.chunk_kb * 1024

    @functools.cached_property
    def queue_bytes(self) -> int:
        return int(self.queue_mb * MB)

    @functools.cached_property
    def sync_bytes(self) -> int:
        return int(self.sync_mb * MB)

    @functools.cached_property
    def min_free_bytes(self) -> int:
        return int(self.min_free_mb * MB)
