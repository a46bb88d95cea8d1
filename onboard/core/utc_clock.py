"""UTC of the autopilot's boot clock, from SYSTEM_TIME samples: ``UTC = boot + offset`` with its 1-sigma.

Pure core: no pymavlink, no sockets, no clocks.  The MAVLink adapter (:mod:`onboard.io.mavlink_link`)
decodes each SYSTEM_TIME (#2) of the autopilot once and feeds :meth:`UtcClock.add_system_time`; the
daemon maps each frame's ``time_boot_us`` (camera frames are stamped on the autopilot's boot clock by
their sender, see :mod:`onboard.core.irframe`; TIMESYNC (:mod:`onboard.core.clock_sync`) is what puts
anything stamped on the companion's own clock there) onto UTC with :meth:`UtcMapping.at`.  The chain
is therefore ``frame -> boot`` (the frame's own stamp) ``-> UTC`` (this module).

Model.  A sample is ``(time_boot_ms, time_unix_usec)`` of one instant of the autopilot.  ``time_boot_ms``
is the boot time truncated to whole milliseconds (PX4 ``hrt_absolute_time() / 1000``, ArduPilot
``millis()``), so the true boot time lies in ``[b, b + 1000)`` us and each sample's offset
``y = unix - (b + 500)`` errs by a uniform quantisation of 1000 / sqrt(12) = 289 us (1 sigma) plus the
autopilot's own jitter between its two reads.  The boot clock runs on the autopilot's crystal and UTC on
GNSS time, so the offset drifts (skew, tens of ppm): the estimate is the least-squares line
``offset(t) = a + b (t - t_mean)`` over the last ``window`` samples, the slope fitted only once they span
``min_skew_span_us`` (before that, an assumed ``skew_sigma_ppm`` enters the sigma instead).

Sigma at boot time ``t`` (:meth:`UtcMapping.at`): ``sqrt(Q^2 + s^2 (1/n + (t - t_mean)^2 / Sxx) +
(k |t - t_mean|)^2)`` with ``Q`` the 289 us quantisation (NOT divided by ``n``: if the samples are sent on
whole milliseconds of the boot clock, as a simulator may, their quantisation errors are all the same),
``s`` the residuals' RMS (at least ``Q``), ``Sxx`` the spread of the sample times (the slope's own
variance; the term is dropped while no slope is fitted) and ``k`` the assumed skew while no slope is fitted.

Refused samples (counted in the shared :class:`~onboard.core.counters.RejectCounter`, never raised):
``utc_no_time`` (``time_unix_usec`` = 0: the autopilot has no GNSS time yet, PX4 and ArduPilot send 0; INFO),
``utc_implausible`` (before ``min_unix_us``, 2020-01-01: a clock that was never set; from
``max_unix_us``, 2100, on; a boot time that is not an integer >= 0), ``utc_duplicate`` (the same boot time as the newest sample: a message
repeated), ``utc_outlier`` (off the fit by more than ``jump_us`` plus 4 sigma), ``utc_step`` (``jump_count``
consecutive outliers that agree with each other within ``jump_us``: UTC itself stepped, e.g. from an RTC
guess to GNSS time; the estimate re-seeds from them).  While outliers are pending (fewer than ``jump_count``),
which clock is right is not known: an outlier may be a wild sample or the first of a step.  The published
mapping keeps its offset but is *disputed*: its sigma takes the largest pending disagreement in quadrature, so
that frames stamped then carry a sigma that covers either reading (a fleet fusion refuses them above its time
bound) instead of the old offset's sub-millisecond sigma; the next agreeing sample or the re-seed ends the
dispute.  A mapping older than ``max_age_us`` of boot time
at the time asked is not used (:meth:`UtcMapping.at` returns None): never a made-up time.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np

from onboard.core.checks import is_nonnegative_number, is_positive_int, require_each
from onboard.core.clock_sync import JumpWindow
from onboard.core.counters import RejectCounter
from onboard.core.errors import ConfigError
from onboard.core.track import Track

__all__ = ["UTC_SOURCE_SYSTEM_TIME", "BOOT_QUANTUM_US", "UtcClockConfig", "UtcMapping", "UtcClock", "with_utc"]

UTC_SOURCE_SYSTEM_TIME = "SYSTEM_TIME"
#: SYSTEM_TIME's time_boot_ms: the boot time truncated to a whole millisecond
BOOT_QUANTUM_US = 1000
_QUANT_SIGMA_US = BOOT_QUANTUM_US / math.sqrt(12.0)  # uniform over one quantum
_GATE_SIGMAS = 4.0


@dataclass(frozen=True)
class UtcClockConfig:
    """The SYSTEM_TIME filter's settings (us of boot time unless named otherwise; module docstring).

        ``window``: samples kept (SYSTEM_TIME comes at about 1 Hz: a minute).  ``min_samples``: samples before a
        mapping is published.  ``jump_us`` / ``jump_count``: the outlier gate and the run of agreeing outliers
        that re-seeds.  ``min_skew_span_us``: history span before the skew is fitted; ``max_skew_ppm`` bounds it;
        ``skew_sigma_ppm``: the drift assumed in the sigma before that.  ``max_age_us``: how far beyond its
        newest sample the mapping is used.  ``min_unix_us``: earlier UTC is a clock that was never set; ``max_unix_us``:
    later is a corrupt field."""

    window: int = 60
    min_samples: int = 3
    jump_us: int = 10_000
    jump_count: int = 3
    min_skew_span_us: int = 10_000_000
    max_skew_ppm: float = 500.0
    skew_sigma_ppm: float = 50.0
    max_age_us: int = 30_000_000
    min_unix_us: int = 1_577_836_800_000_000  # 2020-01-01T00:00:00Z
    max_unix_us: int = 4_102_444_800_000_000  # 2100-01-01T00:00:00Z: later is a corrupt field, not a date

    def __post_init__(self) -> None:
        require_each(
            self,
            (
                "window",
                "min_samples",
                "jump_us",
                "jump_count",
                "min_skew_span_us",
                "max_age_us",
                "min_unix_us",
                "max_unix_us",
            ),
            is_positive_int,
            ConfigError,
            "UtcClockConfig.{name}: expected a positive integer, got {value!r}",
        )
        if self.min_samples > self.window:
            raise ConfigError(f"UtcClockConfig.min_samples ({self.min_samples}) must be <= window ({self.window})")
        require_each(
            self,
            ("max_skew_ppm", "skew_sigma_ppm"),
            is_nonnegative_number,
            ConfigError,
            "UtcClockConfig.{name}: expected a number >= 0, got {value!r}",
        )


@dataclass(frozen=True)
class UtcMapping:
    """One fit of ``UTC - boot`` (immutable: the pipeline thread reads the one the MAVLink thread last made).

    ``offset(t) = offset_mean_us + skew * (t - t_mean_boot_us)``; ``resid_rms_us`` (>= the quantisation),
    ``sxx_us2`` (sum of squared time deviations; 0 when no slope is fitted), ``n_samples``,
    ``newest_boot_us`` / ``oldest_boot_us`` (the samples' span), ``skew_fitted``, ``source``."""

    t_mean_boot_us: float
    offset_mean_us: float
    skew: float
    resid_rms_us: float
    sxx_us2: float
    n_samples: int
    newest_boot_us: int
    oldest_boot_us: int
    skew_fitted: bool
    skew_sigma: float
    max_age_us: int
    source: str = UTC_SOURCE_SYSTEM_TIME
    disputed_us: float = 0.0  # the largest pending outlier's disagreement (module docstring); 0: none

    def offset_us(self, time_boot_us: float) -> float:
        """``UTC - boot`` at boot time ``time_boot_us`` (us)."""
        return self.offset_mean_us + self.skew * (float(time_boot_us) - self.t_mean_boot_us)

    def sigma_us(self, time_boot_us: float) -> float:
        """1-sigma of :meth:`offset_us` (module docstring)."""
        dt = float(time_boot_us) - self.t_mean_boot_us
        var = _QUANT_SIGMA_US**2 + self.resid_rms_us**2 / self.n_samples
        if self.skew_fitted and self.sxx_us2 > 0:
            var += self.resid_rms_us**2 * dt * dt / self.sxx_us2
        else:
            var += (self.skew_sigma * dt) ** 2
        return math.sqrt(var + self.disputed_us**2)

    def at(self, time_boot_us: int) -> tuple[int, int] | None:
        """``(time_unix_us, sigma_us)`` of boot time ``time_boot_us``; None when it is more than ``max_age_us``
        past the newest sample or before the oldest (the mapping does not cover it)."""
        t = int(time_boot_us)
        if t > self.newest_boot_us + self.max_age_us or t < self.oldest_boot_us - self.max_age_us:
            return None
        return t + int(round(self.offset_us(t))), max(1, int(round(self.sigma_us(t))))

    def status(self) -> dict:
        """The daemon status's ``utc`` section: the offset at the newest sample and its sigma."""
        t = self.newest_boot_us
        return {
            "source": self.source,
            "offset_us": int(round(self.offset_us(t))),
            "sigma_us": int(round(self.sigma_us(t))),
            "skew_ppm": round(self.skew * 1e6, 3) if self.skew_fitted else None,
            "samples": self.n_samples,
            "newest_boot_us": t,
            "disputed_us": int(round(self.disputed_us)),
        }


@dataclass(frozen=True)
class _Sample:
    boot_us: int  # time_boot_ms * 1000 (truncated)
    offset_us: int  # unix - (boot + half a quantum)


class UtcClock:
    """Maps the autopilot's boot clock to UTC from SYSTEM_TIME samples (module docstring).

    Step method :meth:`add_system_time`; the current fit is :attr:`mapping` (None until ``min_samples``
    agree), replaced whole on each sample so another thread can read it without a lock."""

    def __init__(self, config: UtcClockConfig | None = None, counter: RejectCounter | None = None) -> None:
        self.config = config if config is not None else UtcClockConfig()
        self.counter = counter if counter is not None else RejectCounter()
        self._window: JumpWindow[_Sample] = JumpWindow()
        self._fitted: UtcMapping | None = None  # the fit the gate tests against (never disputed)
        self.mapping: UtcMapping | None = None  # what frames are stamped with: the fit, or it disputed
        self.steps = 0  # re-seeds on a UTC step
        self.resets = 0  # autopilot reboots (:meth:`reset`)

    def reset(self) -> None:
        """Forget every sample (the boot clock restarted: an autopilot reboot)."""
        self._window.clear()
        self._fitted = self.mapping = None
        self.resets += 1

    def status(self) -> dict:
        """``{state, source, offset_us, sigma_us, skew_ppm, samples, newest_boot_us, disputed_us, steps}``; state ``none``
        (no mapping: its numbers null) or ``ok``."""
        m = self.mapping
        base = (
            {"state": "ok", **m.status()}
            if m is not None
            else {
                "state": "none",
                "source": None,
                "offset_us": None,
                "sigma_us": None,
                "skew_ppm": None,
                "samples": len(self._window.samples),
                "newest_boot_us": None,
                "disputed_us": None,
            }
        )
        base["steps"] = self.steps
        return base

    def add_system_time(self, time_boot_us: int, time_unix_us: int) -> bool:
        """One SYSTEM_TIME: ``time_boot_us`` (= ``time_boot_ms * 1000``) and ``time_unix_us``; True when used."""
        cfg = self.config
        vals = (time_boot_us, time_unix_us)
        if any(isinstance(v, bool) or not isinstance(v, (int, np.integer)) for v in vals) or time_boot_us < 0:
            self.counter.count("utc_implausible", f"time_boot_us={time_boot_us!r} time_unix_us={time_unix_us!r}")
            return False
        boot, unix = int(time_boot_us), int(time_unix_us)
        if unix == 0:
            self.counter.count("utc_no_time", "SYSTEM_TIME without UTC (no GNSS time yet)", level=logging.INFO)
            return False
        if not cfg.min_unix_us <= unix < cfg.max_unix_us:
            self.counter.count(
                "utc_implausible", f"time_unix_us={unix} is before 2020 (a clock never set) or after 2100"
            )
            return False
        if self._window.samples and boot == self._window.samples[-1].boot_us:
            self.counter.count("utc_duplicate", f"a second SYSTEM_TIME at time_boot_ms={boot // 1000}")
            return False
        s = _Sample(boot, unix - boot - BOOT_QUANTUM_US // 2)
        m = self._fitted
        if m is not None:
            err = abs(s.offset_us - m.offset_us(boot))
            if err > cfg.jump_us + _GATE_SIGMAS * m.sigma_us(boot):
                return self._outlier(s, err)
        self._window.accept(s, cfg.window)
        self._fit()
        return True

    def _outlier(self, s: _Sample, err: float) -> bool:
        cfg = self.config
        run = self._window.outliers
        if run and abs(s.offset_us - run[0].offset_us) > cfg.jump_us:
            run.clear()  # a lone wild sample, then another one elsewhere: no agreeing run
        if not self._window.reject(s, cfg.jump_count):
            self.counter.count("utc_outlier", f"SYSTEM_TIME off the UTC estimate by {err / 1000:.1f} ms")
            fit = self._fitted
            if fit is not None:
                disputed = max(abs(o.offset_us - fit.offset_us(o.boot_us)) for o in self._window.outliers)
                self.mapping = replace(fit, disputed_us=disputed)
            return False
        self.counter.count(
            "utc_step",
            f"{cfg.jump_count} SYSTEM_TIME samples agree on a UTC {err / 1000:.1f} ms off: UTC stepped, re-seeded",
        )
        self.steps += 1
        self._fit()
        return True

    def _fit(self) -> None:
        cfg = self.config
        samples = self._window.samples
        n = len(samples)
        if n < cfg.min_samples:
            self._fitted = self.mapping = None
            return
        ref_b, ref_o = samples[0].boot_us, samples[0].offset_us
        x = np.array([p.boot_us - ref_b for p in samples], dtype=float)
        y = np.array([p.offset_us - ref_o for p in samples], dtype=float)
        xm, ym = float(x.mean()), float(y.mean())
        sxx = float(((x - xm) ** 2).sum())
        fitted = bool(x.max() - x.min() >= cfg.min_skew_span_us and sxx > 0)
        b = 0.0
        if fitted:
            lim = cfg.max_skew_ppm * 1e-6
            b = min(max(float(((x - xm) * (y - ym)).sum()) / sxx, -lim), lim)
        r = y - ym - b * (x - xm)
        dof = max(n - (2 if fitted else 1), 1)
        rms = max(math.sqrt(float(r @ r) / dof), _QUANT_SIGMA_US)
        self._fitted = self.mapping = UtcMapping(
            t_mean_boot_us=ref_b + xm,
            offset_mean_us=ref_o + ym,
            skew=b,
            resid_rms_us=rms,
            sxx_us2=sxx if fitted else 0.0,
            n_samples=n,
            newest_boot_us=max(p.boot_us for p in samples),
            oldest_boot_us=min(p.boot_us for p in samples),
            skew_fitted=fitted,
            skew_sigma=cfg.skew_sigma_ppm * 1e-6,
            max_age_us=cfg.max_age_us,
        )


def with_utc(track: Track, mapping: UtcMapping | None) -> Track:
    """``track`` with ``time_unix_us`` / ``time_unix_sigma_us`` of its ``time_boot_us`` through ``mapping``;
    ``track`` itself (its UTC fields None) when there is no mapping or it does not cover that time."""
    if mapping is None:
        return track
    got = mapping.at(track.time_boot_us)
    if got is None:
        return track
    return track.with_time_unix(got[0], got[1])
