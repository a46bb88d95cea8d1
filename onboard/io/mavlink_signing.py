"""MAVLink 2 signing keys from the configuration: one 32-byte key from a file, an environment variable, 64 hex
digits or a passphrase (SHA-256 of it, as MAVProxy's ``signing setup`` and QGroundControl derive it).

Read at the entry point (:class:`~onboard.io.mavlink_link.MavlinkConfig`), never at import; errors are
:class:`~onboard.core.errors.ConfigError` naming the ``mavlink.*`` field.
"""

from __future__ import annotations

import hashlib
import os
import re

from onboard.core.errors import ConfigError

__all__ = ["signing_key_from_text", "load_signing_key"]


def signing_key_from_text(text: str | bytes, field: str) -> bytes:
    """A 32-byte MAVLink 2 signing key from 64 hex digits, 32 raw bytes, or a passphrase (SHA-256 of it,
    as MAVProxy's ``signing setup`` and QGroundControl derive it).  Raises :class:`ConfigError` naming ``field``."""
    if isinstance(text, bytes):
        if len(text) == 32:
            return bytes(text)
        try:
            text = text.decode("utf-8")
        except UnicodeDecodeError:
            raise ConfigError(
                f"{field}: expected 32 raw bytes, 64 hex digits or a passphrase, got {len(text)} undecodable bytes"
            ) from None
    text = text.strip()
    if not text:
        raise ConfigError(f"{field}: expected 32 raw bytes, 64 hex digits or a passphrase, got an empty key")
    if re.fullmatch(r"[0-9a-fA-F]{64}", text):
        return bytes.fromhex(text)
    return hashlib.sha256(text.encode("utf-8")).digest()


def load_signing_key(key_file: str | None, key_env: str | None, environ=None) -> bytes | None:
    """The signing key named by the config (``mavlink.signing_key_file`` / ``mavlink.signing_key_env``), or
    None when neither is set.  Reads the file or the environment: call it at the entry point."""
    environ = os.environ if environ is None else environ
    if key_file and key_env:
        raise ConfigError("mavlink.signing_key_file: set either it or mavlink.signing_key_env, not both")
    if key_file:
        try:
            with open(key_file, "rb") as fh:
                data = fh.read(4096)
        except OSError as exc:
            raise ConfigError(f"mavlink.signing_key_file: cannot read {key_file!r}: {exc.strerror or exc}") from None
        return signing_key_from_text(
            data if len(data) == 32 else data.strip(), f"mavlink.signing_key_file ({key_file})"
        )
    if key_env:
        if key_env not in environ:
            raise ConfigError(f"mavlink.signing_key_env: environment variable {key_env!r} is not set")
        return signing_key_from_text(environ[key_env], f"mavlink.signing_key_env ({key_env})")
    return None
