"""Offset and skew between a local clock and the autopilot's boot clock, from TIMESYNC exchanges.

Pure core: no pymavlink, no sockets.  The MAVLink adapter (:mod:`onboard.io.mavlink_link`) sends the
requests and feeds each answer to :meth:`ClockSync.add_exchange`; the daemon then puts camera frames,
stamped on the local clock (ns), on the autopilot's ``time_boot_us`` with :meth:`ClockSync.to_boot_us`.
The filter's settings are :class:`ClockSyncConfig`.

Rejection reasons (counted in the shared :class:`~onboard.core.counters.RejectCounter`):
``timesync_invalid`` (not integers, or ``tc1`` <= 0), ``timesync_rtt`` (round trip negative or longer
than ``max_rtt_ns``), ``timesync_outlier`` (offset off the estimate by more than ``jump_ns``),
``timesync_reset`` (``jump_count`` such exchanges in a row: the remote clock restarted, the filter
re-seeds from them).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np

from onboard.core.checks import is_positive_int, require_each
from onboard.core.counters import RejectCounter
from onboard.core.errors import ConfigError

__all__ = ["ClockSync", "ClockSyncConfig", "JumpWindow"]

log = logging.getLogger(__name__)

NS_PER_US = 1_000
NS_PER_S = 1_000_000_000

S = TypeVar("S")


@dataclass(frozen=True)
class ClockSyncConfig:
    """TIMESYNC filter settings (ns).

    ``max_rtt_ns``: exchanges with a longer round trip are discarded.  ``window``: exchanges kept.
    ``min_samples``: exchanges before :attr:`ClockSync.synced`.  ``rtt_floor_ns``: weights are
    ``1 / (rtt + rtt_floor)^2``.  ``min_skew_span_ns``: history span before a drift (skew) is fitted.
    ``jump_ns``/``jump_count``: that many consecutive exchanges off the estimate by more than
    ``jump_ns`` (plus half their RTT) mean the remote clock restarted: the filter re-seeds from them.
    """

    max_rtt_ns: int = 50_000_000
    window: int = 64
    min_samples: int = 3
    rtt_floor_ns: int = 200_000
    min_skew_span_ns: int = 20 * NS_PER_S
    max_skew_ppm: float = 1000.0
    jump_ns: int = 50_000_000
    jump_count: int = 3

    def __post_init__(self) -> None:
        require_each(
            self,
            (
                "max_rtt_ns",
                "window",
                "min_samples",
                "rtt_floor_ns",
                "min_skew_span_ns",
                "jump_ns",
                "jump_count",
            ),
            is_positive_int,
            ConfigError,
            "ClockSyncConfig.{name} must be a positive integer, got {value!r}",
        )
        if self.min_samples > self.window:
            raise ConfigError(f"ClockSyncConfig.min_samples ({self.min_samples}) must be <= window ({self.window})")
        if not (math.isfinite(self.max_skew_ppm) and self.max_skew_ppm >= 0):
            raise ConfigError(f"ClockSyncConfig.max_skew_ppm must be >= 0, got {self.max_skew_ppm!r}")


class JumpWindow(Generic[S]):
    """The samples a clock filter fits: the newest ``window`` that agree with the fit, and the run of
    consecutive ones that do not.  A run of ``jump_count`` replaces every sample: the remote clock restarted
    or stepped, and the old samples describe a clock that is gone; a shorter run is outliers, dropped.  The
    one rule of both of the daemon's clock filters (:class:`ClockSync`, :class:`~onboard.core.utc_clock.UtcClock`)."""

    def __init__(self) -> None:
        self.samples: list[S] = []
        self.outliers: list[S] = []

    def accept(self, sample: S, window: int) -> None:
        """``sample`` agrees with the fit: it ends any run of outliers and joins the newest ``window``."""
        self.outliers.clear()
        self.samples.append(sample)
        if len(self.samples) > window:
            del self.samples[: len(self.samples) - window]

    def reject(self, sample: S, jump_count: int) -> bool:
        """``sample`` is off the fit: True when it completes a run of ``jump_count``, which then replaces the
        samples (the caller re-fits); False while the run is shorter (an outlier)."""
        self.outliers.append(sample)
        if len(self.outliers) < jump_count:
            return False
        self.samples = list(self.outliers)
        self.outliers.clear()
        return True

    def clear(self) -> None:
        self.samples.clear()
        self.outliers.clear()


@dataclass
class _Exchange:
    mid_local_ns: int
    offset_ns: int
    rtt_ns: int


class ClockSync:
    """Maps a local clock (ns) to the autopilot boot clock from TIMESYNC exchanges.

    One exchange: we send ``ts1 = local send time`` (tc1 = 0); the autopilot answers with its boot
    time ``tc1`` and our ``ts1`` mirrored; we note the local receive time ``t3``.  Assuming a
    symmetric path, ``offset = tc1 - (ts1 + t3) / 2`` (autopilot minus local, at the midpoint), with
    an error of at most ``rtt / 2`` where ``rtt = t3 - ts1`` (Cristian 1989; MAVLink timesync
    service).  The estimate is a weighted least-squares line ``offset(t) = a + b (t - t_ref)`` over the
    last ``window`` exchanges, weights ``1 / (rtt + floor)^2`` so short round trips dominate; the
    slope ``b`` (clock skew) is fitted only once the history spans ``min_skew_span_ns``.
    PX4 and ArduPilot answer with their boot time in ns, the same clock as ``time_boot_ms``.
    """

    def __init__(self, config: ClockSyncConfig | None = None, counter: RejectCounter | None = None) -> None:
        self.config = config if config is not None else ClockSyncConfig()
        self.counter = counter if counter is not None else RejectCounter()
        self._window: JumpWindow[_Exchange] = JumpWindow()
        self._ref_local_ns = 0
        self._ref_offset_ns = 0
        self._a_ns = 0.0
        self._b = 0.0  # ns of offset per ns of local time
        self.resets = 0
        self._long_rtt_run = 0  # consecutive exchanges discarded for their round trip

    # ------------------------------------------------------------------ state

    @property
    def synced(self) -> bool:
        return len(self._window.samples) >= self.config.min_samples

    @property
    def n_samples(self) -> int:
        return len(self._window.samples)

    @property
    def skew_ppm(self) -> float:
        return self._b * 1e6

    @property
    def min_rtt_ns(self) -> int | None:
        ex = self._window.samples
        return min(e.rtt_ns for e in ex) if ex else None

    def reset(self) -> None:
        """Forget every exchange (call on an autopilot reboot)."""
        self._window.clear()
        self._a_ns, self._b = 0.0, 0.0
        self._long_rtt_run = 0

    # ------------------------------------------------------------------ input

    def add_exchange(self, ts1_local_ns: int, tc1_remote_ns: int, recv_local_ns: int) -> bool:
        """Feed one TIMESYNC round trip; True when it was used."""
        vals = (ts1_local_ns, tc1_remote_ns, recv_local_ns)
        if any(isinstance(v, bool) or not isinstance(v, (int, np.integer)) for v in vals) or tc1_remote_ns <= 0:
            self.counter.count("timesync_invalid", f"ts1={ts1_local_ns!r} tc1={tc1_remote_ns!r} t3={recv_local_ns!r}")
            return False
        ts1, tc1, t3 = (int(v) for v in vals)
        rtt = t3 - ts1
        if rtt < 0 or rtt > self.config.max_rtt_ns:
            # discarded either way; one alone is a moment when either end was busy (typically the first
            # exchange, sent while the autopilot side is still starting): INFO.  Two in a row mean the
            # link itself is slow and the clock may not sync: one WARNING per run of them.
            self._long_rtt_run += 1
            detail = f"round trip {rtt / 1e6:.3f} ms outside [0, {self.config.max_rtt_ns / 1e6:g}] ms"
            self.counter.count("timesync_rtt", detail, level=logging.INFO)
            if self._long_rtt_run == 2:
                log.warning(
                    "timesync_rtt: TIMESYNC round trips too long twice in a row (the last: %s): a slow link or a "
                    "busy CPU; exchanges are discarded while it lasts",
                    detail,
                )
            return False
        self._long_rtt_run = 0
        mid = ts1 + rtt // 2
        ex = _Exchange(mid, tc1 - mid, rtt)
        if self.synced:
            err = abs(ex.offset_ns - self.offset_ns_at(mid))
            if err > self.config.jump_ns + rtt / 2:
                if not self._window.reject(ex, self.config.jump_count):
                    self.counter.count("timesync_outlier", f"offset off the estimate by {err / 1e6:.1f} ms")
                    return False
                self.counter.count(
                    "timesync_reset",
                    f"{self.config.jump_count} consecutive exchanges off by > "
                    f"{self.config.jump_ns / 1e6:g} ms: remote clock restarted",
                )
                self.resets += 1
                self._fit()
                return True
        self._window.accept(ex, self.config.window)
        self._fit()
        return True

    def _fit(self) -> None:
        ex = self._window.samples
        if not ex:
            return
        self._ref_local_ns = ex[0].mid_local_ns
        self._ref_offset_ns = ex[0].offset_ns
        x = np.array([e.mid_local_ns - self._ref_local_ns for e in ex], dtype=float)
        y = np.array([e.offset_ns - self._ref_offset_ns for e in ex], dtype=float)
        w = 1.0 / (np.array([e.rtt_ns for e in ex], dtype=float) + self.config.rtt_floor_ns) ** 2
        w /= w.sum()
        xm, ym = float(w @ x), float(w @ y)
        b = 0.0
        if x.max() - x.min() >= self.config.min_skew_span_ns:
            sxx = float(w @ (x - xm) ** 2)
            if sxx > 0:
                b = float(w @ ((x - xm) * (y - ym))) / sxx
                lim = self.config.max_skew_ppm * 1e-6
                b = min(max(b, -lim), lim)
        self._b = b
        self._a_ns = ym - b * xm

    # ------------------------------------------------------------------ output

    def offset_ns_at(self, local_ns: int) -> int:
        """Estimated ``boot_ns - local_ns`` at local time ``local_ns`` (0 before any exchange)."""
        dx = int(local_ns) - self._ref_local_ns
        return self._ref_offset_ns + int(round(self._a_ns + self._b * dx))

    def to_boot_us(self, local_ns: int) -> int | None:
        """Local clock (ns) -> autopilot ``time_boot_us``; None until synced or when before boot."""
        if not self.synced:
            return None
        boot_ns = int(local_ns) + self.offset_ns_at(local_ns)
        if boot_ns < 0:
            return None
        return (boot_ns + NS_PER_US // 2) // NS_PER_US

    def to_local_ns(self, time_boot_us: int) -> int | None:
        """Inverse of :meth:`to_boot_us` (one fixed-point step; skew is tiny); None until synced."""
        if not self.synced:
            return None
        boot_ns = int(time_boot_us) * NS_PER_US
        guess = boot_ns - self.offset_ns_at(boot_ns - self._ref_offset_ns)
        return boot_ns - self.offset_ns_at(guess)
