"""The daemon's floor on this machine: what its I/O costs when nothing is done with it (``bench.onboard --floor-s S``).

Each case runs in a fresh child interpreter (as the daemon is one), fed as the latency benchmark feeds the
daemon, and its CPU (all threads, from /proc: :func:`bench.onboard._cpu_snapshot`) is timed over ``S`` seconds
after a 3 s settling time:

* ``zenoh frames``: a zenoh session listening on 127.0.0.1 with a subscriber on the frame key whose callback
  does nothing; the parent puts 640 x 512 IRF1 frames at 30 Hz.
* ``zenoh frames + track out``: the same callback copies the payload out (``to_bytes``, as the daemon's) and
  puts a 1.2 kB payload on a publisher declared once (the daemon's frames in and tracks out, nothing between).
* ``MAVLink in``: a thread in ``select`` on a UDP socket reading every datagram (``recvfrom``, nothing parsed);
  the tests' fake autopilot sends attitude / position at 50 / 25 Hz.
* ``pipe round trip``: a thread sends 120 bytes to a child process every 1/15 s and waits for its 120-byte
  answer (the estimator hand-off's wake-ups, with no estimator).
* ``30 Hz sleeper``: a thread that sleeps 1/30 s at a time (a bare wake-up, 30 a second).

Their sum is what the daemon's structure costs before it does anything: the part of its CPU that plumbing
changes cannot remove.  Numbers only; nothing asserts on time.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

__all__ = ["FLOOR_CASES", "floor_child", "bench_floor"]

FLOOR_CASES = ("zenoh frames", "zenoh frames + track out", "MAVLink in", "pipe round trip", "30 Hz sleeper")
SETTLE_S = 3.0


def _echo(conn) -> None:
    while True:
        try:
            data = conn.recv_bytes()
        except (EOFError, OSError):
            return
        conn.send_bytes(data)


def floor_child(case: str, port: int, duration_s: float) -> None:
    """One case's receiving side (run in a child interpreter by :func:`bench_floor`), for ``duration_s``."""
    import select
    import socket

    end = time.monotonic() + duration_s
    if case.startswith("zenoh"):
        from onboard.io.zenoh_session import ZenohConfig, frame_key, open_session, track_key

        session = open_session(ZenohConfig(listen=(f"tcp/127.0.0.1:{port}",)), max_payload_bytes=16 << 20)
        if case == "zenoh frames":
            sub = session.declare_subscriber(frame_key(), lambda sample: None)
        else:
            pub = session.declare_publisher(track_key())
            track = b"x" * 1200

            def on_frame(sample) -> None:
                sample.payload.to_bytes()
                pub.put(track)

            sub = session.declare_subscriber(frame_key(), on_frame)
        time.sleep(max(end - time.monotonic(), 0.0))
        sub.undeclare()
        session.close()
        return
    if case == "MAVLink in":
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", port))
        sock.setblocking(False)
        while time.monotonic() < end:
            if select.select([sock], [], [], 0.05)[0]:
                while True:
                    try:
                        sock.recvfrom(65535)
                    except BlockingIOError:
                        break
        return
    if case == "pipe round trip":
        import multiprocessing as mp

        ctx = mp.get_context("fork")  # a fresh interpreter without threads yet: forking is safe here
        parent, child = ctx.Pipe()
        proc = ctx.Process(target=_echo, args=(child,), daemon=True)
        proc.start()
        row = b"r" * 120

        def loop() -> None:
            n = 0
            t0 = time.monotonic()
            while time.monotonic() < end:
                parent.send_bytes(row)
                if parent.poll(0.05):
                    parent.recv_bytes()
                n += 1
                time.sleep(max(t0 + n / 15.0 - time.monotonic(), 0.0))

        th = threading.Thread(target=loop)
        th.start()
        th.join()
        parent.close()
        proc.join(1.0)
        return
    if case == "30 Hz sleeper":
        n = 0
        t0 = time.monotonic()
        while time.monotonic() < end:
            n += 1
            time.sleep(max(t0 + n / 30.0 - time.monotonic(), 0.0))
        return
    raise ValueError(f"unknown floor case {case!r}")


def _feed(case: str, port: int, until_s: float, scene) -> None:
    """The sending side of ``case`` until ``until_s`` (monotonic), from ``scene`` (``bench.onboard.SyntheticScene``)."""
    if case.startswith("zenoh"):
        import zenoh

        from onboard.io.zenoh_session import ZenohConfig, frame_key, open_session

        payloads = [scene.payload(k) for k in range(8)]
        session = open_session(ZenohConfig(connect=(f"tcp/127.0.0.1:{port}",)))
        pub = session.declare_publisher(frame_key(), congestion_control=zenoh.CongestionControl.BLOCK)
        n, t0 = 0, time.monotonic()
        while time.monotonic() < until_s:
            pub.put(payloads[n % len(payloads)])
            n += 1
            time.sleep(max(t0 + n / 30.0 - time.monotonic(), 0.0))
        pub.undeclare()
        session.close()
    elif case == "MAVLink in":
        from groundsim.io.scripted_autopilot import ScriptedAutopilot

        ap = ScriptedAutopilot(port, scene=scene)
        ap.fly_paced(until_s)  # telemetry only: the floor's receiver reads datagrams and answers nothing
        ap.close()
    else:
        time.sleep(max(until_s - time.monotonic(), 0.0))


def bench_floor(duration_s: float, cpu_snapshot, scene) -> dict[str, float]:
    """Each case's child CPU s per s and wake-ups per s over ``duration_s``; printed, and returned by case.
    ``cpu_snapshot``: ``bench.onboard._cpu_snapshot``; ``scene``: a ``bench.onboard.SyntheticScene`` (the frames
    and the telemetry sent)."""
    from groundsim.io.ports import free_tcp_port, free_udp_port

    print(f"the daemon's floor: its I/O with nothing done, each case in a child interpreter, {duration_s:.0f} s each")
    out: dict[str, float] = {}
    for case in FLOOR_CASES:
        port = free_udp_port() if case == "MAVLink in" else free_tcp_port()
        total_s = SETTLE_S + duration_s + 1.0
        code = f"from bench.onboard_floor import floor_child; floor_child({case!r}, {port}, {total_s})"
        child = subprocess.Popen([sys.executable, "-c", code], env=dict(os.environ), cwd=os.getcwd())
        try:
            time.sleep(1.0)  # the child's session or socket is up
            start = time.monotonic()
            feeder = threading.Thread(
                target=_feed, args=(case, port, start + SETTLE_S + duration_s, scene), daemon=True
            )
            feeder.start()
            time.sleep(SETTLE_S)
            a = cpu_snapshot(child.pid)
            time.sleep(duration_s)
            b = cpu_snapshot(child.pid)
            feeder.join(10.0)
        finally:
            try:
                child.wait(15.0)
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait(5.0)
        span = max(b[0] - a[0], 1e-9)
        cpu = (b[1] - a[1]) / span
        wakes = sum(b[3].values()) - sum(a[3].get(k, 0) for k in b[3])
        out[case] = cpu
        top = sorted(((v - a[2].get(k, 0.0)) / span, k) for k, v in b[2].items())[::-1][:3]
        print(
            f"   {case:26s} {cpu:.4f} CPU s per s, {wakes / span:5.0f} wake-ups per s"
            f" (busiest threads: {', '.join(f'{k} {v:.4f}' for v, k in top if v >= 0.0005) or '-'})"
        )
    floor = sum(v for k, v in out.items() if k != "zenoh frames")
    print(
        f"   the daemon's I/O floor: {floor:.4f} CPU s per s (frames in and tracks out, MAVLink in, the worker's"
        " round trips, one more thread woken per frame)"
    )
    return out
