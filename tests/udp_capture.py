"""A UDP receiver for tests of what the daemon streams (the video transports): every datagram sent to a
port on 127.0.0.1, collected by a thread until :meth:`UdpCapture.close`."""

from __future__ import annotations

import socket
import threading

__all__ = ["UdpCapture"]

RCVBUF_BYTES = 1 << 22  # as the ground-station receivers do: a burst of an IDR frame must not overflow it


class UdpCapture:
    """Binds a free port on 127.0.0.1 (:attr:`port`) and appends each datagram to :attr:`chunks`."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF_BYTES)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)  # how often the thread looks whether it should stop
        self.port: int = self.sock.getsockname()[1]
        self.chunks: list[bytes] = []
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._receive, daemon=True)
        self._thread.start()

    def _receive(self) -> None:
        while not self._done.is_set():
            try:
                self.chunks.append(self.sock.recv(65536))
            except TimeoutError:
                continue

    def close(self, linger_s: float = 0.5) -> None:
        """Takes the datagrams still arriving for ``linger_s``, then stops the thread and closes the socket."""
        self._done.wait(linger_s)
        self._done.set()
        self._thread.join(5)
        self.sock.close()
