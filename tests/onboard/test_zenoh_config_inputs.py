"""A zenoh config file (``--zenoh-config``, the daemon's ``zenoh.config_file``) whose top level is not an object is
refused naming the file, in every command's words, before zenoh reads a JSON5 list as its configuration's fields."""

from __future__ import annotations

import pytest

from onboard.io.zenoh_session import ZenohConfig, ZenohConfigError, build_config, open_session


@pytest.mark.parametrize(
    "name, text, kind",
    [
        ("list.json5", "[1, 2]", "a list"),  # zenoh's own words: "expected An hex string of 1-16 bytes"
        ("empty_list.json5", "// nothing\n/* at all */ [ ]\n", "a list"),  # zenoh takes this as no setting at all
        ("list.json", "[]", "a list"),
        ("bom.json5", '\ufeff"peer"', "a string"),
        ("number.json5", "-1", "a number"),
        ("null.json5", "null", "null"),
        ("list.yaml", "- mode\n- peer\n", "a list"),
        ("flow.yml", "[mode, peer]\n", "a list"),
        ("scalar.yaml", "peer\n", "a string"),
    ],
)
def test_a_top_level_that_is_not_an_object_is_refused_naming_the_file(tmp_path, name, text, kind):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    expected = f"--zenoh-config {path}: its top level is {kind}; expected an object of zenoh settings"
    with pytest.raises(ZenohConfigError) as err:
        open_session(ZenohConfig(config_file=str(path)))  # every command's session: refused before it opens
    assert str(err.value).startswith(expected), err.value
    with pytest.raises(ZenohConfigError, match="^zenoh.config_file .*: its top level is "):
        build_config(ZenohConfig(config_file=str(path)), file_option="zenoh.config_file")


@pytest.mark.parametrize(
    "name, text",
    [("obj.json5", "// a comment first\n{ mode: 'peer' }\n"), ("obj.yaml", "mode: peer\n"), ("bom.json", "\ufeff{}")],
)
def test_an_object_at_the_top_level_is_zenohs_to_read(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    assert build_config(ZenohConfig(config_file=str(path))).get_json("mode") in ('"peer"', "null")


@pytest.mark.parametrize(
    "name, text, zenoh_says",
    [("syntax.json5", "{ mode: ", ""), ("empty.json5", "", "Empty config file"), ("open.json5", "/* [", "")],
)
def test_a_file_that_is_no_value_at_all_is_still_zenohs_to_judge(tmp_path, name, text, zenoh_says):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ZenohConfigError) as err:
        build_config(ZenohConfig(config_file=str(path)))
    assert str(err.value).startswith(f"--zenoh-config {path}: ") and "top level" not in str(err.value)
    assert zenoh_says in str(err.value)


@pytest.mark.parametrize("key", ["root_ca_certificate", "connect_certificate", "connect_private_key"])
def test_a_tls_file_the_configuration_names_must_be_there(tmp_path, key):
    """zenoh reads its TLS files only when a TLS link opens: a certificate missing from a mount passed --check and
    failed the session at start.  Present and readable, the configuration builds."""
    files = {k: tmp_path / f"{k}.pem" for k in ("root_ca_certificate", "connect_certificate", "connect_private_key")}
    for path in files.values():
        path.write_text("-----BEGIN CERTIFICATE-----\n")
    tls = ", ".join(f'{k}: "{p}"' for k, p in files.items())
    cfg = tmp_path / "client.json5"
    cfg.write_text(f'{{ mode: "client", transport: {{ link: {{ tls: {{ {tls}, enable_mtls: true }} }} }} }}\n')
    build_config(ZenohConfig(config_file=str(cfg)))
    files[key].unlink()
    with pytest.raises(ZenohConfigError) as info:
        build_config(ZenohConfig(config_file=str(cfg)))
    assert str(info.value) == f"--zenoh-config {cfg}: transport/link/tls/{key} {files[key]}: no such file"
    files[key].mkdir()
    with pytest.raises(ZenohConfigError, match="a folder, not a file"):
        build_config(ZenohConfig(config_file=str(cfg)))


def test_plain_endpoints_beside_a_client_or_tls_file_are_warned_of(tmp_path, caplog):
    """deploy/README asks for zenoh.connect / zenoh.listen empty with the ACL's client file; left at the shipped
    config's loopback listener, the daemon listened on plain TCP beside the file's session, past the router's access
    control, and nothing said so (a walkthrough of deploy/README)."""
    import logging

    client = tmp_path / "client.json5"
    client.write_text('{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:7447"] } }\n', encoding="utf-8")
    with caplog.at_level(logging.WARNING, "onboard.io.zenoh_session"):
        build_config(ZenohConfig(config_file=str(client), listen=("tcp/127.0.0.1:17449",)))
    (warned,) = [r.getMessage() for r in caplog.records]
    assert "is a client session" in warned and "tcp/127.0.0.1:17449" in warned and "zenoh.listen: []" in warned
    caplog.clear()
    with caplog.at_level(logging.WARNING, "onboard.io.zenoh_session"):
        build_config(ZenohConfig(config_file=str(client)))  # endpoints cleared: the file's alone
        peer = tmp_path / "peer.json5"
        peer.write_text('{ mode: "peer" }\n', encoding="utf-8")
        build_config(ZenohConfig(config_file=str(peer), listen=("tcp/127.0.0.1:17449",)))  # no TLS, no client
    assert caplog.records == []
