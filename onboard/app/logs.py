"""The daemon's log lines: one line per event, text (``ts level= logger= msg=``) or JSON; the same for the
daemon and its estimator process (:func:`setup_logging`)."""

from __future__ import annotations

import json
import logging
import sys
import time

__all__ = ["setup_logging"]


class _TextFormatter(logging.Formatter):
    """``2024-05-01T12:00:00.123Z level=INFO logger=onboard.app.service msg="..."``: one line per event."""

    def format(self, record: logging.LogRecord) -> str:
        ts = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{int(record.msecs):03d}Z"
        msg = record.getMessage()
        if record.exc_info:
            msg += " | " + self.formatException(record.exc_info)
        msg = " ".join(msg.split())
        return f"{ts} level={record.levelname} logger={record.name} msg={json.dumps(msg)}"


class _JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        out = {
            "ts": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{int(record.msecs):03d}Z",
            "level": record.levelname,
            "logger": record.name,
            "msg": record.getMessage(),
        }
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out, separators=(",", ":"))


class _StderrHandler(logging.StreamHandler):
    """A stream handler on ``sys.stderr`` as it is when a record is emitted, not as it was when the handler was
    made: whoever swaps ``sys.stderr`` (a test's capture, a caller redirecting it) closes the old one, and a handler
    holding it would print a 'Logging error' traceback for every record after."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, _value) -> None:
        pass


def setup_logging(level: str, fmt: str) -> None:
    handler = _StderrHandler()
    handler.setFormatter(_JsonFormatter() if fmt == "json" else _TextFormatter())
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)
    # the Foxglove SDK's records about live-view clients (one ERROR per malformed message) are counted, and only the
    # first of each kind logged, by the live view itself (onboard.io.live_view.ClientLog)
