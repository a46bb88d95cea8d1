"""MAVLink 2 signing keys from the configuration: one 32-byte key from a file, an environment variable, 64 hex
digits or a passphrase (SHA-256 of it, as MAVProxy's ``signing setup`` and QGroundControl derive it).

Read at the entry point (:class:`~onboard.io.mavlink_config.MavlinkConfig`), never at import; errors are
:class:`~onboard.core.errors.ConfigError` naming the ``mavlink.*`` field.
"""

from __future__ import annotations

import hashlib
import os
import re

from onboard.core.errors import ConfigError

__all__ = ["SigningKeyError", "signing_key_from_text", "load_signing_key"]

_KEY_FORMS = "32 raw bytes, 64 hex digits or a passphrase"
#: text of hex digits alone this long or longer is a key in hex (and must be 64 digits), not a passphrase
HEX_LOOKING_MIN = 32


class SigningKeyError(ConfigError):
    """A key that cannot be had: ``field`` (``mavlink.signing_key_file`` / ``_env``), what was ``expected``, what was
    ``got`` (where the key came from in it), for the config's one-line error to put together once."""

    def __init__(self, field: str, expected: str, got: str) -> None:
        super().__init__(f"{field}: expected {expected}, got {got}")
        self.field, self.expected, self.got = field, expected, got


def signing_key_from_text(text: str | bytes, field: str, where: str = "") -> bytes:
    """A 32-byte MAVLink 2 signing key from 64 hex digits, 32 raw bytes, or a passphrase (SHA-256 of it,
    as MAVProxy's ``signing setup`` and QGroundControl derive it).  Raises :class:`SigningKeyError` naming ``field``;
    ``where`` (" in FILE") ends what it says was got."""
    if isinstance(text, bytes):
        if len(text) == 32:
            return bytes(text)
        try:
            text = text.decode("utf-8")
        except UnicodeDecodeError:
            raise SigningKeyError(field, _KEY_FORMS, f"{len(text)} undecodable bytes{where}") from None
    text = text.strip()
    if not text:
        raise SigningKeyError(field, _KEY_FORMS, f"an empty key{where}")
    digits = re.sub(r"\s+", "", text)
    if re.fullmatch(r"[0-9a-fA-F]+", digits) and len(digits) >= HEX_LOOKING_MIN:
        # hex digits only: meant as a key in hex (od's spaced output is one), never a passphrase, which a typo in
        # the digits would silently have made of it (62 digits hashed into another key than the autopilot's)
        if len(digits) != 64:
            raise SigningKeyError(field, "64 hex digits for a key in hex", f"{len(digits)} hex digits{where}")
        return bytes.fromhex(digits)
    try:
        passphrase = text.encode("utf-8")
    except UnicodeEncodeError:  # an environment variable's bytes that are not UTF-8 (os.environ's lone surrogates)
        raise SigningKeyError(field, _KEY_FORMS, f"text that is not UTF-8{where}") from None
    return hashlib.sha256(passphrase).digest()


def _is_text_line(data: bytes) -> bool:
    """Whether 32 bytes are a line of text (printable, ending in a newline): a 31-character passphrase and its
    newline, not a raw key (random bytes are all printable with a chance of about 1e-13)."""
    try:
        line = data.decode("utf-8")
    except UnicodeDecodeError:
        return False
    return line.endswith("\n") and line[:-1].rstrip("\r").isprintable()


def load_signing_key(key_file: str | None, key_env: str | None, environ=None) -> bytes | None:
    """The signing key named by the config (``mavlink.signing_key_file`` / ``mavlink.signing_key_env``), or
    None when neither is set.  Reads the file or the environment: call it at the entry point."""
    environ = os.environ if environ is None else environ
    if key_file and key_env:
        raise SigningKeyError(
            "mavlink.signing_key_file", "it or mavlink.signing_key_env, not both", f"both ({key_file!r}, {key_env!r})"
        )
    if key_file:
        try:
            with open(key_file, "rb") as fh:
                data = fh.read(4096)
        except OSError as exc:
            raise SigningKeyError(
                "mavlink.signing_key_file", "a readable key file", f"{key_file!r}: {exc.strerror or exc}"
            ) from None
        return signing_key_from_text(
            data if len(data) == 32 and not _is_text_line(data) else data.strip(),
            "mavlink.signing_key_file",
            f" in {key_file!r}",
        )
    if key_env:
        if key_env not in environ:
            raise SigningKeyError(
                "mavlink.signing_key_env", "the name of a set environment variable", f"{key_env!r}, not set"
            )
        return signing_key_from_text(environ[key_env], "mavlink.signing_key_env", f" in ${key_env}")
    return None
