"""The CPU accounting parsers on sample file contents, the reader on a fake /proc and cgroup tree, and
the ``overload`` warning on counts."""

from __future__ import annotations

import logging
import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from onboard.app.cpu_load import CpuLoad
from onboard.app.watchdog import OVERLOAD_CLEAR_S, Watchdog
from onboard.core.cpu_accounting import (
    parse_cfs_quota,
    parse_cgroup_cpu_stat,
    parse_cpu_max,
    parse_proc_cgroup,
    parse_proc_stat,
    share_per_s,
)
from onboard.core.errors import InputError
from onboard.io.cpu_usage import CpuUsageReader

TICKS_PER_S = 100.0
ATOL_S = 1e-9

# a real /proc/self/stat line (python3, 52 fields)
PROC_STAT = (
    "20379 (python3) R 20362 20362 19308 0 -1 4194304 123 0 0 0 1234 56 78 9 20 0 1 0 1904927 3932160 526 "
    "18446744073709551615 94286720086016 94286720166169 140731478750000 0 0 0 0 0 0 0 0 0 17 1 0 0 0 0 0 "
    "94286720194992 94286720197892 94286904745984 140731478756058 140731478756086 140731478756086 "
    "140731478757355 0\n"
)
V1_CPU_STAT = "nr_periods 23\nnr_throttled 20\nthrottled_time 916747447\nnr_bursts 0\nburst_time 0\n"
V2_CPU_STAT = (
    "usage_usec 5000000\nuser_usec 4000000\nsystem_usec 1000000\nnr_periods 100\nnr_throttled 7\n"
    "throttled_usec 350000\nnr_bursts 0\nburst_usec 0\n"
)


def test_proc_stat_fields():
    t = parse_proc_stat(PROC_STAT)
    assert (t.utime_ticks, t.stime_ticks, t.cutime_ticks, t.cstime_ticks) == (1234, 56, 78, 9)
    assert t.total_s(TICKS_PER_S) == pytest.approx(13.77, abs=ATOL_S)


@given(
    name=st.text(min_size=0, max_size=16).filter(lambda s: "\n" not in s),
    ticks=st.lists(st.integers(0, 2**62), min_size=4, max_size=4),
)
def test_proc_stat_any_command_name(name, ticks):
    """A command name may hold spaces and parentheses: the fields count from the last ')'."""
    line = f"42 ({name}) S 1 1 1 0 -1 0 0 0 0 0 {' '.join(map(str, ticks))} 20 0 1 0 5 6 7\n"
    t = parse_proc_stat(line)
    assert [t.utime_ticks, t.stime_ticks, t.cutime_ticks, t.cstime_ticks] == ticks


@pytest.mark.parametrize(
    "text, expected",
    [
        ("0::/system.slice/irtrack.service\n", (2, "/system.slice/irtrack.service")),
        ("12:pids:/\n4:cpu,cpuacct:/docker/abc\n0::/\n", (1, "/docker/abc")),
        ("1:cpu:/bench\n0::/\n", (1, "/bench")),
        ("3:memory:/x\n", None),
        ("", None),
    ],
)
def test_proc_cgroup(text, expected):
    assert parse_proc_cgroup(text) == expected


# one line's characters: no line break of any kind str.splitlines knows (control characters, line and paragraph
# separators), so a generated line stays one line
LINE_CHARS = st.characters(blacklist_categories=("Cc", "Zl", "Zp"))
# lines near the files' grammar beside plain garbage: random text alone almost never holds a valid line, and a
# check of what comes back would then only ever see None
CGROUP_LINES = st.lists(
    st.one_of(
        st.builds(
            "{}:{}:{}".format,
            st.sampled_from(["0", "0", "1", "12", "x", ""]),  # v2's "0::" often, so it meets v1 lines
            st.sampled_from(["", "", "cpu", "cpu,cpuacct", "cpuacct", "memory"]),
            st.text(LINE_CHARS, max_size=20),
        ),
        st.text(LINE_CHARS, max_size=40),
    ),
    max_size=6,
).map("\n".join)


def _cgroup_lines(text):
    return [line.strip().split(":", 2) for line in text.splitlines()]


@given(st.one_of(st.text(max_size=300), CGROUP_LINES))
def test_proc_cgroup_never_raises_and_returns_a_line_of_the_text(text):
    got = parse_proc_cgroup(text)
    lines = _cgroup_lines(text)
    v1 = [parts for parts in lines if len(parts) == 3 and "cpu" in parts[1].split(",")]
    v2 = [parts for parts in lines if len(parts) == 3 and parts[:2] == ["0", ""]]
    if got is None:
        assert not v1 and not v2
        return
    version, path = got
    assert type(version) is int and type(path) is str
    if version == 1:  # the first line naming the cpu controller: a v1 quota lives there
        assert path == v1[0][2]
    else:
        assert version == 2 and not v1 and path == v2[-1][2]


def test_cpu_stat_v1_and_v2():
    v1 = parse_cgroup_cpu_stat(V1_CPU_STAT)
    assert v1 is not None and (v1.nr_periods, v1.nr_throttled) == (23, 20)
    assert v1.throttled_s == pytest.approx(0.916747447, abs=ATOL_S)
    v2 = parse_cgroup_cpu_stat(V2_CPU_STAT)
    assert v2 is not None and (v2.nr_periods, v2.nr_throttled) == (100, 7)
    assert v2.throttled_s == pytest.approx(0.35, abs=ATOL_S)
    assert parse_cgroup_cpu_stat("usage_usec 5\nuser_usec 4\n") is None


# a token of a counter file: an integer (negative and past 64 bits too), or a word
TOKENS = st.one_of(st.integers(-(2**65), 2**65).map(str), st.text(LINE_CHARS, min_size=1, max_size=6))
PROC_STAT_LINES = st.builds(
    "{} ({}) {}".format,
    st.integers(1, 2**22),
    # a command name may hold spaces and parentheses
    st.one_of(st.text(st.sampled_from("a1() "), max_size=8), st.text(LINE_CHARS, max_size=12)),
    st.one_of(  # counts only (most parse), or counts among words and negative numbers
        st.lists(st.integers(0, 2**64).map(str), min_size=13, max_size=20),
        st.lists(st.one_of(st.integers(0, 2**64).map(str), TOKENS), min_size=13, max_size=20),
    ).map(" ".join),
)
CPU_STAT_LINES = st.lists(
    st.builds(
        "{} {}".format,
        st.sampled_from(["nr_periods", "nr_throttled", "throttled_usec", "throttled_time", "usage_usec", "x"]),
        TOKENS,
    ),
    max_size=6,
).map("\n".join)


@given(st.one_of(st.text(max_size=300), PROC_STAT_LINES))
def test_proc_stat_garbage_raises_input_error_only_and_returns_counts(text):
    try:
        got = parse_proc_stat(text)
    except InputError:
        return
    ticks = (got.utime_ticks, got.stime_ticks, got.cutime_ticks, got.cstime_ticks)
    assert all(type(t) is int and t >= 0 for t in ticks)
    # fields 14-17, counted after the command name's last ')'
    assert list(ticks) == [int(f) for f in text[text.rfind(")") + 1 :].split()[11:15]]


def _is_counter(parts, names):
    if len(parts) != 2 or parts[0] not in names:
        return False
    try:
        int(parts[1])
    except ValueError:
        return False
    return True


@given(st.one_of(st.text(max_size=300), CPU_STAT_LINES))
def test_cpu_stat_garbage_raises_input_error_only_and_returns_counts(text):
    try:
        got = parse_cgroup_cpu_stat(text)
    except InputError:
        return
    if got is None:  # only when no line is a throttled-time counter
        assert not any(_is_counter(line.split(), ("throttled_usec", "throttled_time")) for line in text.splitlines())
        return
    assert type(got.nr_periods) is int and type(got.nr_throttled) is int and type(got.throttled_s) is float
    assert got.nr_periods >= 0 and got.nr_throttled >= 0
    assert math.isfinite(got.throttled_s) and got.throttled_s >= 0.0


@given(quota_us=st.integers(1, 10**7), period_us=st.integers(1000, 10**6))
def test_quota_round_trip(quota_us, period_us):
    cores = quota_us / period_us
    assert parse_cpu_max(f"{quota_us} {period_us}\n") == pytest.approx(cores)
    assert parse_cfs_quota(f"{quota_us}\n", f"{period_us}\n") == pytest.approx(cores)


@pytest.mark.parametrize(
    "bad, words",
    [
        ("", "expected"),
        ("max", "expected"),
        ("50000", "expected"),
        ("a b", "not integers"),
        # integers out of range say so (they were reported as 'not integers')
        ("0 100000", "must be positive"),
        ("-5 100000", "must be positive"),
        ("5 0", "must be positive"),
    ],
)
def test_cpu_max_refused(bad, words):
    with pytest.raises(InputError, match=words):
        parse_cpu_max(bad)


def test_no_quota():
    assert parse_cpu_max("max 100000\n") is None
    assert parse_cfs_quota("-1\n", "100000\n") is None


def test_share_per_s():
    assert share_per_s(1.0, 1.5, 2.0) == pytest.approx(0.25)
    assert share_per_s(None, 1.0, 1.0) is None
    assert share_per_s(2.0, 1.0, 1.0) is None  # a counter that went back
    assert share_per_s(1.0, 2.0, 0.0) is None


def _tree(tmp_path, version: int, stat_ticks: int, throttled: str, quota: tuple[str, str], periods=(10, 4)):
    proc = tmp_path / "proc" / "self"
    proc.mkdir(parents=True, exist_ok=True)
    (proc / "stat").write_text(f"1 (onboard) S 0 0 0 0 -1 0 0 0 0 0 {stat_ticks} 0 0 0 20 0 1 0 5\n")
    root = tmp_path / "cg"
    if version == 1:
        (proc / "cgroup").write_text("3:cpu,cpuacct:/bench/daemon\n0::/\n")
        d = root / "cpu,cpuacct" / "bench" / "daemon"
        d.mkdir(parents=True, exist_ok=True)
        (d / "cpu.cfs_quota_us").write_text(quota[0])
        (d / "cpu.cfs_period_us").write_text(quota[1])
        (d / "cpu.stat").write_text(f"nr_periods {periods[0]}\nnr_throttled {periods[1]}\nthrottled_time {throttled}\n")
    else:
        (proc / "cgroup").write_text("0::/bench\n")
        d = root / "bench"
        d.mkdir(parents=True, exist_ok=True)
        (d / "cpu.max").write_text(f"{quota[0]} {quota[1]}\n")
        (d / "cpu.stat").write_text(
            f"usage_usec 1\nnr_periods {periods[0]}\nnr_throttled {periods[1]}\nthrottled_usec {throttled}\n"
        )
    return tmp_path / "proc", root


@pytest.mark.parametrize("version, throttled0, throttled1", [(1, "0", "500000000"), (2, "0", "500000")])
def test_reader_and_load(tmp_path, version, throttled0, throttled1):
    proc, root = _tree(tmp_path, version, 100, throttled0, ("25000", "100000"))
    load = CpuLoad(CpuUsageReader(proc, root))
    first = load.sample(10.0, worker_cpu_s=0.0)
    assert first["gets_share"] is None and first["quota_cores"] == pytest.approx(0.25)
    # +0.5 s of process CPU at 100 ticks/s; the quota ran out in 5 of the 20 periods it ran in
    _tree(tmp_path, version, 150, throttled1, ("25000", "100000"), periods=(30, 9))
    s = load.sample(12.0, worker_cpu_s=0.2)
    ticks = load.reader._ticks_per_s
    assert s["gets_share"] == pytest.approx((50 / ticks + 0.2) / 2.0)
    assert s["throttled_share"] == pytest.approx(0.25)
    assert s["throttled_periods"] == 5 and s["throttled_periods_share"] == pytest.approx(0.25)
    # the quota bound: it needed more than it got, by how much the kernel's counters do not say (throttled_time is
    # summed over the CPUs' run queues to the end of each period: gets + throttled overstated it ~4x)
    assert s["needs_share"] is None and load.quota_bound() is True
    assert "quota ran out in 25 % of its periods" in load.words() and "quota of 0.25 cores" in load.words()
    # a quota that did not bind: it got what it needed
    _tree(tmp_path, version, 200, throttled1, ("25000", "100000"), periods=(50, 9))
    s = load.sample(14.0, worker_cpu_s=0.4)
    assert s["needs_share"] == pytest.approx(s["gets_share"]) and s["throttled_periods"] == 0
    assert load.quota_bound() is False and "ran out" not in load.words()
    # an extra status 30 ms later (a warning raised): the last figures stand, not a window of three clock ticks
    _tree(tmp_path, version, 260, throttled1, ("25000", "100000"), periods=(51, 9))
    assert load.sample(14.03, worker_cpu_s=0.4) == s
    # counters that went back (a cgroup recreated): unknown, not a negative count
    _tree(tmp_path, version, 250, throttled1, ("25000", "100000"), periods=(3, 1))
    s = load.sample(16.0, worker_cpu_s=0.6)
    assert s["throttled_periods"] is None and s["throttled_periods_share"] is None and load.quota_bound() is None


def test_reader_without_cgroup(tmp_path):
    (tmp_path / "proc" / "self").mkdir(parents=True)
    r = CpuUsageReader(tmp_path / "proc", tmp_path / "none").read()
    assert r.process_cpu_s is None and r.throttled_s is None and r.quota_cores is None


def _watchdog(caplog) -> Watchdog:
    return Watchdog(
        started_s=0.0,
        frame_key="irtrack/v/frames",
        zenoh_where="peer",
        mavlink_connection="udpin:127.0.0.1:14540",
        camera_size_px=(640, 512),
        logger=logging.getLogger("test.overload"),
    )


def test_overload_raised_on_the_first_growth_and_cleared(caplog):
    wd = _watchdog(caplog)
    caplog.set_level(logging.INFO, "test.overload")
    wd.load(0.0, frames_dropped=0, estimates_stale=0)
    wd.load(0.5, frames_dropped=0, estimates_stale=0)
    assert not wd.active
    wd.load(1.0, frames_dropped=3, estimates_stale=0, cpu_words=" (it got 0.25 of a core)")
    (w,) = wd.active
    assert w.code == "overload" and "3 frames dropped" in w.message and "cpus" in w.message
    wd.load(1.5, frames_dropped=3, estimates_stale=2)
    assert "2 positions withheld" in wd.active[0].message and "3 frames dropped" in wd.active[0].message
    wd.load(1.5 + OVERLOAD_CLEAR_S / 2, frames_dropped=3, estimates_stale=2)
    assert wd.active
    wd.load(1.5 + OVERLOAD_CLEAR_S, frames_dropped=3, estimates_stale=2)
    assert not wd.active
    warned = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1  # logged once


def test_overload_names_a_silent_estimator_worker_instead_of_the_cpu(caplog):
    """Positions withheld as too old while no frame is dropped and the worker has answered nothing for a while (a
    stopped or stalled process): the message blamed the CPU (a failure-injection audit: SIGSTOP on the worker,
    throttled share 0)."""
    wd = _watchdog(caplog)
    wd.load(0.0, frames_dropped=0, estimates_stale=0)
    wd.load(0.5, frames_dropped=0, estimates_stale=4, cpu_words=" (it got 0.18 of a core)", estimator_silent_s=1.6)
    (w,) = wd.active
    assert "worker process has answered nothing for 1.6 s" in w.message and "cpus" not in w.message
    wd.load(1.0, frames_dropped=2, estimates_stale=8, estimator_silent_s=2.1)  # frames dropped too: the CPU's words
    assert "does not get the CPU it needs" in wd.active[0].message


def test_overload_names_a_stall_of_the_whole_process_instead_of_the_cpu_share(caplog):
    """A daemon stopped 3 s (SIGSTOP, a paused VM) dropped frames and was told it 'does not get the CPU it needs (it
    got 0.24 of a core)', with advice to raise its CPU limit (a fault-injection audit)."""
    wd = _watchdog(caplog)
    wd.load(0.0, frames_dropped=0, estimates_stale=0)
    wd.load(3.5, frames_dropped=20, estimates_stale=2, cpu_words=" (it got 0.24 of a core)", stalled_s=3.04)
    (w,) = wd.active
    assert "stood still for 3.0 s (its process stopped, or this computer paused or swapped)" in w.message
    assert "cpus" not in w.message and "0.24 of a core" not in w.message
    wd.load(4.0, frames_dropped=25, estimates_stale=2, stalled_s=0.0)  # losing frames on, no stall: the CPU's words
    assert "does not get the CPU it needs" in wd.active[0].message


@pytest.mark.parametrize(
    "quota_bound, says, not_said",
    [
        (True, "cpus", "did not run out"),
        (None, "cpus", "did not run out"),
        (False, "other work on this computer", "cpus"),
    ],
)
def test_overload_advice_follows_whether_the_quota_ran_out(caplog, quota_bound, says, not_said):
    """With no quota holding it back (the counters say the quota never ran out), raising the CPU limit cannot help:
    the first advice was that all the same (an audit starving the daemon with other processes, no quota)."""
    wd = _watchdog(caplog)
    wd.load(0.0, frames_dropped=0, estimates_stale=0)
    wd.load(1.0, frames_dropped=3, estimates_stale=0, quota_bound=quota_bound)
    (w,) = wd.active
    assert says in w.message and not_said not in w.message


def test_a_v1_container_finds_its_cgroup_at_the_controllers_mount_root(tmp_path, caplog):
    """cgroup v1 has no cgroup namespace: in a container /proc/self/cgroup names the host's /docker/<id>, while the
    container's own cgroup is the controller's mount root. The reader found no cpu.stat, and the quota and its
    throttling read null, as if there were no limit, without a word (an audit)."""
    proc = tmp_path / "proc" / "self"
    proc.mkdir(parents=True)
    (proc / "stat").write_text("1 (onboard) S 0 0 0 0 -1 0 0 0 0 0 100 0 0 0 20 0 1 0 5\n")
    (proc / "cgroup").write_text("12:cpu,cpuacct:/docker/abc123\n0::/\n")
    root = tmp_path / "cg"
    d = root / "cpu,cpuacct"
    d.mkdir(parents=True)
    (d / "cpu.stat").write_text("nr_periods 100\nnr_throttled 40\nthrottled_time 2000000000\n")
    (d / "cpu.cfs_quota_us").write_text("50000\n")
    (d / "cpu.cfs_period_us").write_text("100000\n")
    r = CpuUsageReader(tmp_path / "proc", root)
    assert r.cgroup_dir == d
    reading = r.read()
    assert reading.quota_cores == pytest.approx(0.5) and reading.nr_throttled == 40 and reading.nr_periods == 100
    # no cpu.stat anywhere: null, and said once
    with caplog.at_level(logging.WARNING, "onboard.io.cpu_usage"):
        assert CpuUsageReader(tmp_path / "proc", tmp_path / "empty").cgroup_dir is None
    assert any("no cpu.stat" in rec.getMessage() for rec in caplog.records)


def test_overload_names_frames_arriving_in_bursts_instead_of_the_cpu(caplog):
    """Frames the link held and released ten at once overflowed the 4-frame queue: 111 of 300 dropped in a 10 s
    burst phase, and the daemon was told it 'does not get the CPU it needs' (a frame-stream audit). Drops the
    receiver saw arrive bunched are named as such; a drop of frames that came at the camera's pace is the CPU's."""
    wd = _watchdog(caplog)
    wd.load(0.0, frames_dropped=0, estimates_stale=0)
    wd.load(1.0, frames_dropped=6, estimates_stale=0, cpu_words=" (it got 0.22 of a core)", frames_dropped_bunched=6)
    (w,) = wd.active
    assert "arrived in bursts" in w.message and "input.queue_length" in w.message and "0.22 of a core" in w.message
    assert "CPU it needs" not in w.message
    wd.load(2.0, frames_dropped=8, estimates_stale=0, frames_dropped_bunched=6)  # 2 more, at the camera's pace
    assert "does not get the CPU it needs" in wd.active[0].message
    # a CPU quota that ran out stops the receiving thread too, which bunches the frames: the CPU's words
    wd.load(3.0, frames_dropped=12, estimates_stale=0, frames_dropped_bunched=10, quota_bound=True)
    assert "does not get the CPU it needs" in wd.active[0].message and "cpus" in wd.active[0].message
