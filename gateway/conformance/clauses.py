r"""The clauses of docs/device-spec.md as checks, each numbered as the clause it tests.

A check talks to the device through a :class:`Probe`, and either returns (pass), raises
:class:`Failed` with what it expected, or raises :class:`Skipped` when the device offers
nothing to check it on (no read-only property, no model). Checks run in the order of
:data:`CLAUSES`; the early ones learn what the later ones need (the property names, the model)
into :class:`Device`. The checksum checks come last: they leave the device in checksum mode
until the last of them ends it with a plain ``HELLO``.

Every check keeps to what the device promised: one request at a time, lines no longer than its
``maxline`` (but the one that tests the limit) written in pieces its ``rxbuf`` holds; a SET only
of a value the device must refuse or of the value it holds already, and none with ``read_only``.
"""

from __future__ import annotations

import math
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from functools import partial

from gateway.conformance.probe import Heard, Probe, checked, is_error
from services.kernel.errors import Code, PropertyError
from services.kernel.line_protocol import BadLine, ErrorReply, Frame, Hello, Ok, Pong, crc8
from services.kernel.model import Access, PropertyModel, ServiceModel
from services.kernel.model_codec import model_from_text
from services.kernel.values.grammar import parse_names, parse_number

#: Properties read one by one to find those a GET answers; a device lists a few dozen at most.
READ_AT_MOST = 24
#: Names no device has: the kit's own namespace.
MISSING = "conformance.no_such_property"


class Failed(Exception):
    """The device broke the clause: ``what`` it should have done."""

    def __init__(self, what: str) -> None:
        super().__init__(what)
        self.what = what


class Skipped(Exception):
    """The device offers nothing this clause can be checked on."""

    def __init__(self, why: str) -> None:
        super().__init__(why)
        self.why = why


@dataclass
class Device:
    """What the checks learned about the device so far."""

    greeting: Hello
    #: The kit may SET values (only ones a conforming device refuses, or holds already).
    writes: bool = True
    #: What ``GET properties`` listed.
    names: list[str] = field(default_factory=list)
    #: Paths whose GET answered OK, with the value text.
    values: dict[str, str] = field(default_factory=dict)
    #: What ``GET properties.model`` described; None when the device does not describe itself.
    model: ServiceModel | None = None

    def described(self, wanted: Callable[[PropertyModel], bool]) -> list[PropertyModel]:
        """The model's properties that ``wanted`` picks (none without a model)."""
        return [p for p in self.model.properties if wanted(p)] if self.model is not None else []


Check = Callable[[Probe, Device], Awaitable[None]]


@dataclass(frozen=True, slots=True)
class Clause:
    """One check of one clause of docs/device-spec.md."""

    number: str
    title: str
    check: Check


CLAUSES: list[Clause] = []


def clause(number: str, title: str) -> Callable[[Check], Check]:
    """Register the decorated check as clause ``number`` of docs/device-spec.md."""

    def register(check: Check) -> Check:
        CLAUSES.append(Clause(number, title, check))
        return check

    return register


# -- expectations ------------------------------------------------------------------------------


def _expect(
    heard: Heard | None, what: str, good: Callable[[Frame | BadLine], bool], probe: Probe
) -> Frame | BadLine:
    if heard is None:
        raise Failed(f"{what}; nothing came within {probe.timeout:g} s")
    frame = heard.frame
    if not good(frame):
        raise Failed(what)
    return frame


def _expect_error(heard: Heard | None, code: Code, tag: str | None, probe: Probe) -> None:
    tagged = f"#{tag} " if tag else ""
    _expect(
        heard,
        f"{tagged}ERR {int(code)} ...{'' if tag else ' (untagged)'}",
        lambda _: is_error(heard, code, tag),
        probe,
    )


def _expect_ok(heard: Heard | None, tag: str, probe: Probe) -> Ok:
    frame = _expect(heard, f"#{tag} OK ...", lambda f: type(f) is Ok and f.tag == tag, probe)
    assert type(frame) is Ok
    return frame


async def _expect_exact(probe: Probe, send: bytes, answer: bytes) -> None:
    heard = await probe.ask(send)
    _expect(heard, f"`{answer.decode()}` exactly", lambda _: heard is not None and heard.raw == answer, probe)


async def _expect_silence(probe: Probe, send: bytes) -> None:
    """``send`` gets no reply: the next reply is the PONG of a PING sent after it."""
    await probe.send(send)
    tag = probe.tag()
    heard = await probe.ask(f"#{tag} PING".encode())
    _expect(
        heard,
        f"no reply to it: the next reply `#{tag} PONG`",
        lambda f: type(f) is Pong and f.tag == tag,
        probe,
    )


def _number(text: str) -> float | None:
    try:
        return parse_number(text)
    except (PropertyError, ValueError):
        return None


def _text(value: str | bytes) -> str:
    return value if isinstance(value, str) else ""


# -- 4 the greeting, and HELLO -----------------------------------------------------------------


@clause("3.7", "`HELLO` is answered with the greeting, `HELLO foo` with ERR 3")
async def hello_request(probe: Probe, device: Device) -> None:
    heard = await probe.ask(b"HELLO")
    _expect(
        heard, "the greeting `HELLO 1 ...`, untagged", lambda f: type(f) is Hello and f.tag is None, probe
    )
    _expect_error(await probe.ask(b"HELLO foo"), Code.INVALID_ARGUMENT, None, probe)


@clause("4.3", "a greeting sent to the device gets no reply")
async def greeting_to_device(probe: Probe, device: Device) -> None:
    await _expect_silence(probe, b"HELLO 1 name=conformance type=kit")


# -- 2.3 tags, 3.6 PING ---------------------------------------------------------------------------


@clause("2.3", "a reply carries its request's tag, a greeting's too")
async def tags_echoed(probe: Probe, device: Device) -> None:
    tag = probe.tag()
    heard = await probe.ask(f"#{tag} HELLO".encode())
    _expect(heard, f"`#{tag} HELLO 1 ...`", lambda f: type(f) is Hello and f.tag == tag, probe)
    tag = probe.tag()
    heard = await probe.ask(f"#{tag} PING".encode())
    _expect(heard, f"`#{tag} PONG`", lambda f: type(f) is Pong and f.tag == tag, probe)
    tag = "A_z-9"  # every kind of tag character
    heard = await probe.ask(f"#{tag} PING".encode())
    _expect(heard, f"`#{tag} PONG`", lambda f: type(f) is Pong and f.tag == tag, probe)


@clause("2.3", "a bad tag is answered ERR 3, untagged")
async def bad_tags(probe: Probe, device: Device) -> None:
    for line in (b"# PING", b"#123456789 PING", b"#a+b PING", b"#k0"):
        _expect_error(await probe.ask(line), Code.INVALID_ARGUMENT, None, probe)


@clause("3.6", "PING data is echoed byte for byte")
async def ping_echo(probe: Probe, device: Device) -> None:
    tag = probe.tag()
    data = r"conformance a\sb\\c  d"
    await _expect_exact(probe, f"#{tag} PING {data}".encode(), f"#{tag} PONG {data}".encode())
    await _expect_exact(probe, b"PING", b"PONG")


# -- 1 lines ----------------------------------------------------------------------------------------


@clause("1.1", "a CR before the LF is removed")
async def cr_lf(probe: Probe, device: Device) -> None:
    tag = probe.tag()
    await _expect_exact(probe, f"#{tag} PING crlf\r".encode(), f"#{tag} PONG crlf".encode())


@clause("1.3", "an empty line and a line of spaces get no reply")
async def empty_lines(probe: Probe, device: Device) -> None:
    await probe.send(b"")
    await _expect_silence(probe, b"   ")


@clause("1.4", "spaces before the first field and between fields are skipped")
async def spaces(probe: Probe, device: Device) -> None:
    tag = probe.tag()
    await _expect_exact(probe, f"   #{tag}   PING x".encode(), f"#{tag} PONG x".encode())


@clause("1.2", "a line over `maxline` is answered ERR 8 with its tag, and the next is read")
async def line_too_long(probe: Probe, device: Device) -> None:
    tag = probe.tag()
    head = f"#{tag} GET ".encode()
    line = head + b"a" * (device.greeting.max_line + 8 - len(head))
    _expect_error(await probe.ask(line), Code.RESOURCE_EXHAUSTED, tag, probe)
    tag = probe.tag()
    heard = await probe.ask(f"#{tag} PING".encode())
    _expect(heard, f"`#{tag} PONG` after the long line", lambda f: type(f) is Pong and f.tag == tag, probe)


# -- 2, 3.10: words, paths, bad lines -------------------------------------------------------------------


@clause("2.2", "words are taken in any case")
async def word_case(probe: Probe, device: Device) -> None:
    tag = probe.tag()
    await _expect_exact(probe, f"#{tag} pInG w".encode(), f"#{tag} PONG w".encode())


@clause("3.10", "an unknown word is ERR 12 with the request's tag")
async def unknown_word(probe: Probe, device: Device) -> None:
    tag = probe.tag()
    _expect_error(await probe.ask(f"#{tag} FROB x".encode()), Code.UNIMPLEMENTED, tag, probe)


@clause("2.5", "text after the path of a GET is ERR 3")
async def extra_field(probe: Probe, device: Device) -> None:
    tag = probe.tag()
    _expect_error(await probe.ask(f"#{tag} GET {MISSING} extra".encode()), Code.INVALID_ARGUMENT, tag, probe)


@clause("3.9", "OK, ERR, EVENT and GONE sent to a device are ERR 3")
async def replies_to_device(probe: Probe, device: Device) -> None:
    tag = probe.tag()
    _expect_error(await probe.ask(f"#{tag} OK 5".encode()), Code.INVALID_ARGUMENT, tag, probe)
    for line in (b"ERR 5 conformance", f"EVENT {MISSING} 1".encode(), f"GONE {MISSING}".encode()):
        _expect_error(await probe.ask(line), Code.INVALID_ARGUMENT, None, probe)


@clause("3.9", "a PONG sent to a device gets no reply")
async def pong_to_device(probe: Probe, device: Device) -> None:
    await _expect_silence(probe, b"PONG")


@clause("3.8", "`#TAG CANCEL` gets no reply (or ERR 12); untagged CANCEL is ERR 3")
async def cancel(probe: Probe, device: Device) -> None:
    tag = probe.tag()
    await probe.send(f"#{tag} CANCEL".encode())
    after = probe.tag()
    heard = await probe.ask(f"#{after} PING".encode())
    if is_error(heard, Code.UNIMPLEMENTED, tag):  # a device that does not know the word (§3.8)
        heard = await probe.reply()
    _expect(
        heard,
        f"no reply to the CANCEL: the next reply `#{after} PONG`",
        lambda f: type(f) is Pong and f.tag == after,
        probe,
    )
    _expect_error(await probe.ask(b"CANCEL"), Code.INVALID_ARGUMENT, None, probe)


# -- 3.1, 9: what the device has -----------------------------------------------------------------


@clause("3.1", "GET of a path the device lacks is ERR 5")
async def get_missing(probe: Probe, device: Device) -> None:
    tag = probe.tag()
    _expect_error(await probe.ask(f"#{tag} GET {MISSING}".encode()), Code.NOT_FOUND, tag, probe)


def _read_or_refused(frame: Frame | BadLine, tag: str) -> bool:
    """``#TAG OK ...`` or ``#TAG ERR 9 ...``: a listed property that reads, or one that never does."""
    if type(frame) is Ok:
        return frame.tag == tag
    return type(frame) is ErrorReply and frame.code == Code.FAILED_PRECONDITION and frame.tag == tag


@clause("3.1", "`GET properties` lists names, and each answers GET with OK or ERR 9")
async def get_properties(probe: Probe, device: Device) -> None:
    tag = probe.tag()
    heard = await probe.ask(f"#{tag} GET properties".encode())
    if is_error(heard, Code.NOT_FOUND, tag):
        raise Skipped("the device lists no properties (`GET properties` is ERR 5; a SHOULD)")
    ok = _expect_ok(heard, tag, probe)
    try:
        device.names = parse_names(_text(ok.value))
    except PropertyError as exc:
        raise Failed(f"a names list `(a b c)`: {exc.message}") from None
    for name in device.names[:READ_AT_MOST]:
        tag = probe.tag()
        heard = await probe.ask(f"#{tag} GET {name}".encode())
        frame = _expect(
            heard,
            f"`#{tag} OK ...` or `#{tag} ERR 9 ...` for a listed property",
            partial(_read_or_refused, tag=tag),
            probe,
        )
        if type(frame) is Ok:
            device.values[name] = _text(frame.value)


@clause("9", "`GET properties.model` is a model, or ERR 5")
async def get_model(probe: Probe, device: Device) -> None:
    tag = probe.tag()
    heard = await probe.ask(f"#{tag} GET properties.model".encode())
    if is_error(heard, Code.NOT_FOUND, tag):
        raise Skipped("the device does not describe itself (a MAY)")
    ok = _expect_ok(heard, tag, probe)
    try:
        device.model = model_from_text(_text(ok.value), device.greeting.type)
    except PropertyError as exc:
        raise Failed(f"a model `((name type access ...) ...)`: {exc.message}") from None


@clause("2.2", "paths are case-sensitive: a listed path in upper case is ERR 5")
async def path_case(probe: Probe, device: Device) -> None:
    names = [n for n in device.values if n.upper() != n and n.upper() not in device.names]
    if not names:
        raise Skipped("no readable listed property with a lower-case letter")
    tag = probe.tag()
    _expect_error(await probe.ask(f"#{tag} GET {names[0].upper()}".encode()), Code.NOT_FOUND, tag, probe)


@clause("3.1", "GET of an action is ERR 9 (reads never act)")
async def get_action(probe: Probe, device: Device) -> None:
    actions = device.described(lambda p: p.access is Access.ACTION)
    if not actions:
        raise Skipped("no action in the model")
    tag = probe.tag()
    _expect_error(
        await probe.ask(f"#{tag} GET {actions[0].name}".encode()), Code.FAILED_PRECONDITION, tag, probe
    )


# -- 3.2 SET -------------------------------------------------------------------------------------


def _writes(device: Device) -> None:
    if not device.writes:
        raise Skipped("--read-only: no SET is sent")


@clause("3.2", "SET of a read-only property is ERR 9")
async def set_read_only(probe: Probe, device: Device) -> None:
    _writes(device)
    read_only = device.described(lambda p: p.access is Access.READ and p.name in device.values)
    if not read_only:
        raise Skipped("no read-only property the device answers GET for")
    name = read_only[0].name
    tag = probe.tag()
    line = f"#{tag} SET {name} {device.values[name]}".encode()  # its own value: nothing changes either way
    _expect_error(await probe.ask(line), Code.FAILED_PRECONDITION, tag, probe)


def _writable_numbers(device: Device) -> list[PropertyModel]:
    return device.described(
        lambda p: (
            p.access is Access.READ_WRITE and p.type in ("number", "integer") and p.name in device.values
        )
    )


@clause("3.2", "SET of a number above the property's maximum is ERR 3, and changes nothing")
async def set_out_of_range(probe: Probe, device: Device) -> None:
    _writes(device)
    bounded = [p for p in _writable_numbers(device) if p.maximum is not None and math.isfinite(p.maximum)]
    if not bounded:
        raise Skipped("no read-write number with a maximum in the model")
    prop = bounded[0]
    assert prop.maximum is not None
    above = prop.maximum + max(abs(prop.maximum), 1.0)
    tag = probe.tag()
    _expect_error(
        await probe.ask(f"#{tag} SET {prop.name} {above:g}".encode()), Code.INVALID_ARGUMENT, tag, probe
    )
    tag = probe.tag()
    ok = _expect_ok(await probe.ask(f"#{tag} GET {prop.name}".encode()), tag, probe)
    if _number(_text(ok.value)) == above:
        raise Failed(f"{prop.name} unchanged by the refused SET")


@clause("3.2", "SET of the value a property holds answers OK with that value")
async def set_same_value(probe: Probe, device: Device) -> None:
    _writes(device)
    numbers = _writable_numbers(device)
    if not numbers:
        raise Skipped("no read-write number in the model")
    prop = numbers[0]
    held = device.values[prop.name]
    tag = probe.tag()
    ok = _expect_ok(await probe.ask(f"#{tag} SET {prop.name} {held}".encode()), tag, probe)
    if _number(_text(ok.value)) != _number(held):
        raise Failed(f"`#{tag} OK {held}`: the value as stored")


# -- 3.3, 3.4 LISTEN and UNLISTEN ----------------------------------------------------------------------


def _listenable(device: Device) -> str:
    described = device.described(
        lambda p: p.access in (Access.READ, Access.READ_WRITE) and p.type != "namespace"
    )
    names = [p.name for p in described if p.name in device.values] or list(device.values)
    if not names:
        raise Skipped("no property the device answers GET for")
    return names[0]


@clause("3.3", "LISTEN is answered OK and the value (twice alike); UNLISTEN OK; push=0: ERR 12")
async def listen(probe: Probe, device: Device) -> None:
    name = _listenable(device)
    tag = probe.tag()
    heard = await probe.ask(f"#{tag} LISTEN {name}".encode())
    if not device.greeting.push:
        _expect_error(heard, Code.UNIMPLEMENTED, tag, probe)
        return
    _expect_ok(heard, tag, probe)
    tag = probe.tag()
    _expect_ok(await probe.ask(f"#{tag} LISTEN {name}".encode()), tag, probe)
    tag = probe.tag()
    _expect_ok(await probe.ask(f"#{tag} UNLISTEN {name}".encode()), tag, probe)


@clause("3.4", "UNLISTEN of a path not listened to is OK")
async def unlisten_unknown(probe: Probe, device: Device) -> None:
    tag = probe.tag()
    _expect_ok(await probe.ask(f"#{tag} UNLISTEN {MISSING}".encode()), tag, probe)


# -- 6 checksums (last: they end in checksum mode until the plain HELLO) ----------------------------


def _is_checked(heard: Heard | None) -> bool:
    return heard is not None and heard.raw.lstrip(b" ").startswith(b"$")


@clause("6.2", "a `$` line with a wrong checksum is `$ERR 15`, untagged, and turns no mode on")
async def damaged_checksum(probe: Probe, device: Device) -> None:
    tag = probe.tag()
    good = checked(f"#{tag} PING b")
    damaged = good[:-2] + (b"00" if good[-2:] != b"00" else b"11")
    heard = await probe.ask(damaged)
    _expect_error(heard, Code.DATA_LOSS, None, probe)
    if not _is_checked(heard):
        raise Failed("the ERR 15 with a checksum: `$ERR 15 ...*HH` (§6.4)")
    tag = probe.tag()
    heard = await probe.ask(f"#{tag} PING".encode())
    _expect(
        heard,
        f"a plain `#{tag} PONG`: a damaged line turns no mode on (§6.5)",
        lambda f: type(f) is Pong and not _is_checked(heard),
        probe,
    )


@clause("6.3", "a space after `$` is ERR 3, untagged")
async def space_after_dollar(probe: Probe, device: Device) -> None:
    tag = probe.tag()
    body = f" #{tag} PING".encode()
    heard = await probe.ask(b"$" + body + b"*%02X" % crc8(body))
    _expect_error(heard, Code.INVALID_ARGUMENT, None, probe)


@clause("6.3", "a `$` line over `maxline` is ERR 8, untagged")
async def long_checked_line(probe: Probe, device: Device) -> None:
    tag = probe.tag()
    head = f"#{tag} GET "
    line = checked(head + "a" * (device.greeting.max_line + 8 - len(head)))
    heard = await probe.ask(line)
    _expect_error(heard, Code.RESOURCE_EXHAUSTED, None, probe)


@clause("6.4", "the reply to a `$` line carries the right checksum and the tag")
async def mirrored(probe: Probe, device: Device) -> None:
    tag = probe.tag()
    heard = await probe.ask(checked(f"#{tag} PING a"))
    _expect(
        heard,
        f"`$#{tag} PONG a*HH`",
        lambda f: type(f) is Pong and f.tag == tag and f.data == "a" and _is_checked(heard),
        probe,
    )


@clause("6.5", "after a good `$` line every line goes out checked, until a plain HELLO")
async def checksum_mode(probe: Probe, device: Device) -> None:
    tag = probe.tag()
    _expect(await probe.ask(checked(f"#{tag} PING")), f"`$#{tag} PONG*HH`", lambda f: type(f) is Pong, probe)
    tag = probe.tag()
    heard = await probe.ask(f"#{tag} PING b".encode())
    _expect(
        heard,
        f"`$#{tag} PONG b*HH` in checksum mode",
        lambda f: type(f) is Pong and f.tag == tag and _is_checked(heard),
        probe,
    )
    heard = await probe.ask(b"HELLO")
    _expect(
        heard,
        "the greeting, plain: a plain HELLO ends checksum mode",
        lambda f: type(f) is Hello and not _is_checked(heard),
        probe,
    )
    tag = probe.tag()
    heard = await probe.ask(f"#{tag} PING".encode())
    _expect(
        heard,
        f"a plain `#{tag} PONG`",
        lambda f: type(f) is Pong and f.tag == tag and not _is_checked(heard),
        probe,
    )
