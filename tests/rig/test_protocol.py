"""The protocol helpers: command encoding and the parsing of banners, replies and states."""

from __future__ import annotations

import pytest

from psmini.errors import RigError
from psmini.rig.protocol import (
    Identity,
    encode_command,
    parse_banner,
    parse_identity,
    parse_reply,
    parse_state,
)


def test_encode_commands_are_ascii_lines():
    assert encode_command("PING") == b"PING\n"
    assert encode_command("ON", 7) == b"ON 7\n"
    assert encode_command("ID?") == b"ID?\n"
    assert isinstance(encode_command("WDT", 500), bytes)


@pytest.mark.parametrize(
    "verb, args", [("on", (1,)), ("ON", (-1,)), ("ON", (1.5,)), ("ON", (True,)), ("WDT", (10**40,))]
)
def test_encode_refuses_bad_commands(verb, args):
    with pytest.raises(RigError):
        encode_command(verb, *args)


def test_banner_and_identity():
    identity = parse_banner("READY psmini-leds 1.0.0 leds=8 wdt=2000")
    assert identity == Identity("psmini-leds", "1.0.0", 8, 2000)
    assert str(identity) == "psmini-leds 1.0.0 leds=8 wdt=2000"
    assert parse_identity(str(identity)) == identity
    assert parse_banner("OK PING") is None
    assert parse_banner("READY something else") is None


def test_replies():
    ok = parse_reply("OK ON 3")
    assert (ok.ok, ok.verb, ok.text, ok.code) == (True, "ON", "3", 0)
    assert parse_reply("OK PING").text == ""
    error = parse_reply("ERR 2 led index out of range")
    assert (error.ok, error.code, error.text) == (False, 2, "led index out of range")
    for noise in ("", "OK ", "ERR x y", "READY psmini-leds 1.0.0 leds=8 wdt=2000", "PING"):
        assert parse_reply(noise) is None


def test_state():
    assert parse_state("on=3 wdt=2000 trips=0").lit == 3
    assert parse_state("on=- wdt=100 trips=2").lit is None
    assert parse_state("on=all wdt=100 trips=2").trips == 2
    with pytest.raises(RigError, match="expected a state"):
        parse_state("on=x")
