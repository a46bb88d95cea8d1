"""Properties of onboard.io.mavlink_signing (hypothesis): whatever a key file or an environment variable holds, the
key is 32 bytes or a :class:`SigningKeyError` (a ConfigError) naming the ``mavlink.*`` field, never another
exception; 32 raw bytes are the key as they are, 64 hex digits (any case, any whitespace between) the key they spell,
anything else that is not hex-looking the SHA-256 of the stripped passphrase."""

from __future__ import annotations

import hashlib
import os
import tempfile

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from onboard.io.mavlink_signing import HEX_LOOKING_MIN, SigningKeyError, load_signing_key, signing_key_from_text

FIELD = "mavlink.signing_key_env"
keys = st.binary(min_size=32, max_size=32)
# text as an environment variable can hold it: os.environ decodes bytes that are not UTF-8 as lone surrogates
env_text = st.one_of(
    st.text(max_size=80),
    st.text(st.characters(codec="utf-8"), max_size=80),
    st.builds(lambda b: b.decode("utf-8", "surrogateescape"), st.binary(max_size=40)),
)


def _key_or_refused(get) -> bytes | None:
    try:
        key = get()
    except SigningKeyError as exc:
        assert exc.field.startswith("mavlink.signing_key_"), exc.field
        assert str(exc).startswith(f"{exc.field}: expected ")
        return None
    assert type(key) is bytes and len(key) == 32
    return key


@settings(max_examples=150, deadline=None)
@given(env_text)
@example("\udcff")  # the byte 0xff in the environment: its UTF-8 encoding raised UnicodeEncodeError
@example("pass\udce9word")
def test_any_text_is_a_key_or_refused_naming_the_field(text):
    key = _key_or_refused(lambda: signing_key_from_text(text, FIELD, " in $K"))
    stripped = text.strip()
    digits = "".join(stripped.split())
    hex_looking = len(digits) >= HEX_LOOKING_MIN and all(c in "0123456789abcdefABCDEF" for c in digits)
    if key is not None and not hex_looking:
        assert key == hashlib.sha256(stripped.encode("utf-8")).digest()  # MAVProxy's and QGroundControl's


@settings(max_examples=100, deadline=None)
@given(env_text)
def test_any_environment_value_is_a_key_or_refused_naming_the_field(text):
    _key_or_refused(lambda: load_signing_key(None, "K", {"K": text}))


@settings(max_examples=80, deadline=None)
@given(keys, st.booleans(), st.lists(st.sampled_from([" ", "\n", "\t", "  "]), min_size=63, max_size=63))
def test_64_hex_digits_spell_the_key_in_any_case_and_spacing(key, upper, gaps):
    digits = key.hex().upper() if upper else key.hex()
    spaced = "".join(d + (g if i % 2 else "") for i, (d, g) in enumerate(zip(digits, [*gaps, ""]))) + "\n"
    assert signing_key_from_text(spaced, FIELD) == key
    assert signing_key_from_text(spaced.encode(), FIELD) == key


@settings(max_examples=80, deadline=None)
@given(keys, st.integers(HEX_LOOKING_MIN, 80).filter(lambda n: n != 64))
def test_hex_digits_of_another_count_are_refused_not_hashed(key, n):
    digits = (key.hex() * 2)[:n]
    with pytest.raises(SigningKeyError, match=f"{n} hex digits"):
        signing_key_from_text(digits, FIELD)


@settings(max_examples=100, deadline=None)
@given(st.one_of(keys, st.binary(max_size=100), env_text.map(lambda t: t.encode("utf-8", "surrogateescape"))))
@example(b"\xff" * 31 + b"\n")  # 32 bytes ending in a newline, not text: a raw key
@example(b"a" * 31 + b"\n")  # a 31-character passphrase and its newline
def test_any_key_file_is_a_key_or_refused_and_32_raw_bytes_are_the_key(data):
    fd, path = tempfile.mkstemp(prefix="irtrack-key-")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        key = _key_or_refused(lambda: load_signing_key(path, None, {}))
    finally:
        os.unlink(path)
    text_line = data.endswith(b"\n") and data[:-1].rstrip(b"\r").decode("utf-8", "replace").isprintable()
    if len(data) == 32 and not text_line:
        assert key == data
