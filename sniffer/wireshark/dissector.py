"""A Wireshark Lua dissector for Progwhiz, generated from the analyzer's own tables.

The Lua logic (``frames.lua``, ``session.lua`` and ``tree.lua`` beside this
module: framing, decoding, the per-conversation session, the tree) is fixed; what it knows of the protocol comes from
the table this module writes in front of it, taken from ``analyzer/protocol``:
the rules (ids, severities, summaries), the messages (titles, fields, one-line
descriptions), the codes and ranges of the codec, the framer's tokens and
limits, the handshake's transition table, which way each kind of item
travels, which answer each request waits for, and the checksum rules.  So a
rule or a message added to the analyzer reaches Wireshark by generating the
dissector again, and the tests compare what tshark says with what the
analyzer says on the same recording (docs/wireshark.md).
"""

from __future__ import annotations

import dataclasses
import re
from importlib import resources
from typing import Any

from whiztap.analyzer import __version__
from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol import codec, framing, handshake
from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.checksum import CHECKSUM_RULES, DEFAULT_CHECKSUM_RULE
from whiztap.analyzer.protocol.observations import Direction, direction_violation
from whiztap.analyzer.protocol.pairing import answer_spec
from whiztap.analyzer.protocol.rules import RULES, Severity

DEFAULT_PORT = 5000  # whiztap sim's
# Each checksum rule in Lua, over the entries' Dev# and unit type bytes: the
# Python rules are functions, so each needs its twin here (a test checks they agree).
LUA_CHECKSUMS = {
    "dev-sum": "function(entries) local s = 0 for _, e in ipairs(entries) do s = s + e.device end return s % 256 end",
    "dev-unit-sum": "function(entries) local s = 0 for _, e in ipairs(entries) do s = s + e.device + e.unit_type end "
                    "return s % 256 end",
    "dev-sum-7bit": "function(entries) local s = 0 for _, e in ipairs(entries) do s = s + e.device end "
                    "return s % 128 end",
}
# The fixed Lua logic, in the order it is put together: framing and decoding
# (a function of its own, for Lua's limit of 200 locals in one), the session, the tree.
LOGIC = ("frames.lua", "session.lua", "tree.lua")
_SENTINEL = 1000001  # a value no field has, to find where describe() puts each field
_SEVERITY = {Severity.ERROR: "error", Severity.WARNING: "warn", Severity.INFO: "note"}


class DissectorError(WhiztapError, ValueError):
    """The dissector cannot be generated as asked; one line for the user."""


def _message_classes() -> list[type[m.Message]]:
    return [c for c in vars(m).values()
            if isinstance(c, type) and issubclass(c, m.Message) and c is not m.Message and c.title]


def _blank(cls: type[m.Message]) -> m.Message:
    """A message of ``cls`` with every field 0: enough to ask what it waits for."""
    return cls(**{f.name: 0 for f in dataclasses.fields(cls)}) if dataclasses.is_dataclass(cls) else cls()


def _describe_template(cls: type[m.Message]) -> str | None:
    """``describe()`` with each int field as ``{name}`` (None for a message
    with fields of other types, which the Lua describes itself)."""
    fields: tuple[dataclasses.Field, ...] = dataclasses.fields(cls) if dataclasses.is_dataclass(cls) else ()
    if any(f.type not in ("int", int) for f in fields):
        return None
    values = {f.name: _SENTINEL + i for i, f in enumerate(fields)}
    text = cls(**values).describe()
    for name, value in values.items():
        text = text.replace(str(value), "{" + name + "}")
    return text


def _snake(name: str) -> str:
    return re.sub(r"(?<!^)(?=[A-Z])", "_", name).lower()


def _fields() -> list[dict[str, str]]:
    """A ProtoField per message field: ints shared by name (``progwhiz.channel``
    is every message's channel), records' fields under the record's name
    (``progwhiz.channel_config.unit_type``), other fields under the message's."""
    out: dict[str, dict[str, str]] = {}
    for cls in _message_classes():
        fields: tuple[dataclasses.Field, ...] = dataclasses.fields(cls) if dataclasses.is_dataclass(cls) else ()
        for f in fields:
            if f.type in ("int", int):
                out.setdefault(f.name, {"key": f.name, "type": "uint32", "name": f.name.replace("_", " ").title()})
            elif str(f.type).startswith("tuple["):
                record = getattr(m, str(f.type)[6:].split(",")[0])
                for sub in dataclasses.fields(record):
                    key = f"{_snake(record.__name__)}.{sub.name}"
                    out.setdefault(key, {"key": key, "type": "uint32", "name": sub.name.replace("_", " ").title()})
            else:
                key = f"{_snake(cls.__name__)}.{f.name}"
                out.setdefault(key, {"key": key, "type": "bytes" if f.type == "bytes" else "string",
                                     "name": f"{cls.title} {f.name}"})
    return list(out.values())


def _handshake() -> dict[str, Any]:
    table: dict[str, dict[str, list[Any]]] = {}
    for (state, step), (after, rule) in handshake.HANDSHAKE_TABLE.items():
        table.setdefault(state.value, {})[step.value] = [after.value, rule or False]
    return {
        "table": table,
        "mode_told": {f"{state.value} {step.value}": mode.value for (state, step), mode in handshake.MODE_TOLD.items()},
        "expected": {state.value: text for state, text in handshake.EXPECTED_IN_STATE.items()},
        "step_words": {step.value: text for step, text in handshake.STEP_WORDS.items()},
        "server_steps": {word.decode(): step.value for word, step in handshake.SERVER_STEPS.items()},
    }


def _protocol() -> dict[str, Any]:
    """The codec's and framer's numbers and tokens."""
    return {
        "codes": {"fetch_config": codec.FETCH_CONFIG_CODE, "fetch_camera": codec.FETCH_CAMERA_CODE,
                  "servo_position": codec.SERVO_POSITION_CODE, "stop_internal": codec.STOP_INTERNAL,
                  "stop_external": codec.STOP_EXTERNAL,
                  "internal": [codec.INTERNAL_SCRIPTS.start, codec.INTERNAL_SCRIPTS.stop - 1],
                  "external": [codec.EXTERNAL_SCRIPTS.start, codec.EXTERNAL_SCRIPTS.stop - 1]},
        "max": {"channel": codec.MAX_CHANNEL, "send_value": codec.MAX_SEND_VALUE, "sensor": codec.MAX_SENSOR_DATA,
                "servo": codec.MAX_SERVO_DATA, "config_channels": codec.MAX_CONFIG_CHANNELS,
                "device": codec.MAX_DEVICE},
        "field_widths": list(codec.FIELD_WIDTHS),
        "headers": {"command": codec.encode(m.FetchConfiguration())[:4].decode(),
                    "response": codec.encode(m.ChannelResponse(0, 0))[:4].decode(),
                    "config": codec.encode(m.ConfigurationSettings(()))[:4].decode()},
        "framing": {"words": [w.decode() for w in handshake.HANDSHAKE_WORDS], "trailer": framing.TRAILER.decode(),
                    "set_config_prefix": framing.SET_CONFIG_PREFIX.decode(),
                    "set_config_trailer": framing.SET_CONFIG_TRAILER.decode(), "layout_data1": framing.LAYOUT_DATA1,
                    "text_frame_max": framing.TEXT_FRAME_MAX, "max_item": framing.DEFAULT_MAX_ITEM,
                    "max_image": framing.DEFAULT_MAX_IMAGE, "jpeg": framing.JPEG_SOI.decode("latin-1"),
                    "png": framing.PNG_SIGNATURE.decode("latin-1")},
        "unframed_rules": {reason.value: codec.decode(framing.ItemKind.UNFRAMED, b"x", reason).violations[0].rule_id
                           for reason in framing.Unframed},
        "kind_words": {kind.value: kind.words for kind in framing.ItemKind},
        "travels": {kind.value: direction.value for kind in framing.ItemKind for direction in Direction
                    if direction_violation(kind, direction) is None
                    and direction_violation(kind, Direction.S2C if direction is Direction.C2S else Direction.C2S)},
        "units": {int(u): str(u) for u in m.UnitType},
        "unit_of_command": {cls.__name__: int(u) for cls, u in codec.UNIT_OF_COMMAND.items()},
        "answer_kind": {cls.__name__: kind.value for cls in _message_classes()
                        if (kind := answer_spec(_blank(cls), ())[0]) is not None},
    }


def tables(port: int = DEFAULT_PORT, checksum_rule: str = DEFAULT_CHECKSUM_RULE,
           answer_timeout_ms: int = 5000) -> dict[str, Any]:
    """Everything the Lua logic knows of the protocol, as plain data."""
    if checksum_rule not in CHECKSUM_RULES:
        raise DissectorError(f"unknown checksum rule {checksum_rule!r}: expected one of {', '.join(CHECKSUM_RULES)}")
    missing = set(CHECKSUM_RULES) - set(LUA_CHECKSUMS)
    if missing:
        raise DissectorError(f"no Lua twin for the checksum rule(s) {', '.join(sorted(missing))}")
    return {
        "version": __version__,
        "defaults": {"port": port, "checksum_rule": checksum_rule, "answer_timeout_ms": answer_timeout_ms},
        "rules": [{"id": r.id, "severity": _SEVERITY[r.severity], "section": r.section, "summary": r.summary}
                  for r in RULES.values()],
        "messages": {cls.__name__: {"title": cls.title, "sender": cls.sender, "describe": _describe_template(cls)}
                     for cls in _message_classes()},
        "fields": _fields(),
        "checksum_rules": [{"name": r.name, "description": r.description} for r in CHECKSUM_RULES.values()],
        "handshake": _handshake(),
        **_protocol(),
    }


def lua_literal(value: Any) -> str:
    """Plain data (dicts, lists, strings, numbers, booleans, None) as a Lua expression."""
    if value is None:
        return "nil"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return '"' + "".join(c if 0x20 <= ord(c) < 0x7F and c not in '"\\' else f"\\{ord(c):03d}"
                             for c in value) + '"'
    if isinstance(value, list | tuple):
        return "{" + ", ".join(lua_literal(v) for v in value) + "}"
    if isinstance(value, dict):
        return "{" + ", ".join(f"[{lua_literal(k)}] = {lua_literal(v)}" for k, v in value.items()) + "}"
    raise TypeError(f"no Lua literal for {value!r}")


def generate(port: int = DEFAULT_PORT, checksum_rule: str = DEFAULT_CHECKSUM_RULE,
             answer_timeout_ms: int = 5000) -> str:
    """The whole dissector: a header, the generated table ``T``, the checksum
    rules and the fixed logic."""
    data = tables(port, checksum_rule, answer_timeout_ms)
    checksums = ", ".join(f"[{lua_literal(name)}] = {LUA_CHECKSUMS[name]}" for name in CHECKSUM_RULES)
    folder = resources.files("whiztap.sniffer.wireshark")
    frames, session, tree = (folder.joinpath(name).read_text(encoding="utf-8") for name in LOGIC)
    unknown = set(re.findall(r"\bM\.(\w+)", frames + session + tree)) - set(data["messages"])
    if unknown:  # the logic names a message the analyzer no longer has
        raise DissectorError(f"the Lua logic names unknown message(s) {', '.join(sorted(unknown))}")
    return (f"-- Progwhiz Robotics Server API dissector for Wireshark, generated by whiztap {__version__}\n"
            f"-- ('whiztap wireshark-dissector'; docs/wireshark.md).  Do not edit: generate it again.\n"
            f"-- Load it with: wireshark -X lua_script:progwhiz.lua  (or copy it into your Lua plugins folder)\n\n"
            f"local T = {lua_literal(data)}\nlocal CHECKSUMS = {{{checksums}}}\n\n"
            f"local P = (function()\n{frames}end)()\n\n{session}\n{tree}")
