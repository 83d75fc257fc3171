"""JSON Schema of the JSON report (version 1).  Tests validate output against it."""

_INT = {"type": "integer"}
_NS_OR_NULL = {"type": ["integer", "null"]}
_STR = {"type": "string"}
_SEVERITY = {"type": "string", "enum": ["error", "warning", "info"]}
_COUNTS = {"type": "object", "additionalProperties": _INT}
_SIDE = {"type": "string", "enum": ["client", "server"],
         "description": "whose conduct the violation is about"}

_BY_SEVERITY = {"type": "object", "required": ["error", "warning", "info"],
                "properties": {"error": _INT, "warning": _INT, "info": _INT}}
_LATENCY = {"type": "array", "items": {
    "type": "object",
    "required": ["request", "count", "mean_ns", "p50_ns", "p95_ns", "p99_ns", "max_ns"],
    "properties": {"request": _STR, "count": _INT, "mean_ns": _INT, "p50_ns": _INT, "p95_ns": _INT,
                   "p99_ns": _INT, "max_ns": _INT},
}}

_INTERVENTIONS = {
    "type": "object",
    "required": ["count", "connections", "causes", "effect_counts", "effects", "effects_not_listed",
                 "effects_by_severity", "fail_on_interventions"],
    "properties": {
        "count": _INT, "connections": _INT,
        "causes": {"type": "array", "items": {
            "type": "object", "required": ["cause", "count", "actions"],
            "properties": {"cause": _STR, "count": _INT, "actions": _COUNTS}}},
        "effect_counts": _COUNTS,
        "effects": {"type": "array", "items": {
            "type": "object",
            "required": ["rule_id", "severity", "section", "file", "conn", "dir", "t_ns", "t_rel_s", "frame",
                         "detail", "late", "seen_by", "cause"],
            "properties": {"rule_id": _STR, "seen_by": _SIDE,
                           "cause": {"type": "string",
                                     "description": "the intervention it follows from ('' when not known)"}}}},
        "effects_not_listed": _INT,
        "effects_by_severity": _BY_SEVERITY,
        "fail_on_interventions": {"type": "boolean", "description": "whether the effects fail the report"},
    },
}

_DAY = {"type": ["string", "null"], "description": "YYYY-MM-DD (UTC); null when no time is known"}
_FLEET = {"type": "array", "items": {
    "type": "object", "required": ["group_by", "day_of", "groups"], "additionalProperties": False,
    "properties": {
        "group_by": {"type": "array", "items": _STR, "minItems": 1},
        "day_of": {"const": "start_time"},
        "groups": {"type": "array", "items": {
            "type": "object",
            "required": ["group", "recordings", "connections", "frames", "violations", "violations_by_severity",
                         "passed", "rules", "days"],
            "properties": {
                "group": {"type": "object", "additionalProperties": {"type": ["string", "null"]}},
                "recordings": _INT, "connections": _INT, "frames": _INT, "violations": _INT,
                "violations_by_severity": _BY_SEVERITY, "passed": {"type": "boolean"},
                "rules": {"type": "array", "items": {
                    "type": "object", "required": ["rule_id", "severity", "count", "since", "last"],
                    "properties": {"rule_id": _STR, "severity": _SEVERITY, "count": _INT, "since": _DAY,
                                   "last": _DAY}}},
                "days": {"type": "array", "items": {
                    "type": "object",
                    "required": ["day", "recordings", "connections", "frames", "violations", "rule_counts"],
                    "properties": {"day": _DAY, "recordings": _INT, "connections": _INT, "frames": _INT,
                                   "violations": _INT, "rule_counts": _COUNTS}}},
            },
        }},
    },
}}

REPORT_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "$id": "whiztap.report/1",
    "title": "whiztap conformance report",
    "type": "object",
    "required": ["schema", "version", "whiztap_version", "spec_revision", "files", "checksum_rule",
                 "severity_threshold", "ignored_rules", "passed", "summary", "connections", "rule_counts",
                 "violations", "violations_not_listed", "latency", "unanswered", "set_configurations",
                 "per_file"],
    "additionalProperties": False,
    "properties": {
        "schema": {"const": "whiztap.report"},
        "version": {"const": 1},
        "whiztap_version": _STR,
        "spec_revision": _STR,
        "files": {"type": "array", "items": _STR},
        "checksum_rule": {"type": "object", "required": ["name", "description"],
                          "properties": {"name": _STR, "description": _STR}},
        "severity_threshold": _SEVERITY,
        "ignored_rules": {"type": "array", "items": _STR},
        "assumed_channels": _STR,
        "passed": {"type": "boolean"},
        "summary": {
            "type": "object",
            "required": ["connections", "frames", "first_ns", "last_ns", "duration_s", "frames_by_kind",
                         "violations_by_severity"],
            "properties": {
                "connections": _INT, "frames": _INT, "first_ns": _NS_OR_NULL, "last_ns": _NS_OR_NULL,
                "duration_s": {"type": "number"},
                "frames_by_kind": {"type": "object", "required": ["c2s", "s2c"],
                                   "properties": {"c2s": _COUNTS, "s2c": _COUNTS}},
                "violations_by_severity": {"type": "object", "required": ["error", "warning", "info"],
                                           "properties": {"error": _INT, "warning": _INT, "info": _INT}},
            },
        },
        "connections": {"type": "array", "items": {
            "type": "object",
            "required": ["file", "conn", "client", "upstream", "mode", "handshake", "first_ns", "last_ns",
                         "frames", "violations", "channel_map", "closed_by", "notes"],
            "properties": {
                "file": _STR, "conn": _INT, "client": _STR, "upstream": _STR,
                "mode": {"type": "string", "enum": ["unknown", "winsock", "vpn"]}, "handshake": _STR,
                "first_ns": _NS_OR_NULL, "last_ns": _NS_OR_NULL, "frames": _INT, "violations": _COUNTS,
                "channel_map": {"type": "object", "additionalProperties": {
                    "type": "object", "required": ["unit_type", "unused", "switch_type"],
                    "properties": {"unit_type": _INT, "unused": _INT, "switch_type": _INT}}},
                "closed_by": _STR, "notes": {"type": "array", "items": _STR},
                # only for a connection the proxy stood in the middle of: the changes it made
                "interventions": _INT,
            },
        }},
        "rule_counts": _COUNTS,
        "violations": {"type": "array", "items": {
            "type": "object",
            "required": ["rule_id", "severity", "section", "file", "conn", "dir", "t_ns", "t_rel_s", "frame",
                         "detail", "late"],
            "properties": {
                "rule_id": {"type": "string", "pattern": "^PW-[A-Z0-9-]+$"}, "severity": _SEVERITY,
                "section": _STR, "file": _STR, "conn": _INT,
                "dir": {"type": ["string", "null"], "enum": ["c2s", "s2c", None]},
                "t_ns": _INT, "t_rel_s": {"type": "number"},
                "index": {"type": "integer", "description": "the item's position in its connection's session"},
                "frame": {"type": "string", "description": "the frame's bytes, escaped"},
                "detail": _STR, "late": {"type": "boolean"}, "side": _SIDE,
            },
        }},
        "violations_not_listed": _INT,
        # the server's latency: from the request as it received it to the answer it sent
        "latency": _LATENCY,
        # only when the proxy stood in the middle: the client's, from the request it sent to the answer it received
        "client_latency": _LATENCY,
        "unanswered": _COUNTS,
        "set_configurations": {"type": "array", "items": {
            "type": "object", "required": ["file", "conn", "t_ns", "checksum", "expected", "ok", "satisfies"],
            "properties": {"file": _STR, "conn": _INT, "t_ns": _INT, "checksum": _INT, "expected": _INT,
                           "ok": {"type": "boolean"}, "satisfies": {"type": "array", "items": _STR}},
        }},
        "per_file": {"type": "array", "items": {
            "type": "object", "required": ["file", "connections", "frames", "violations"],
            "properties": {"file": _STR, "connections": _INT, "frames": _INT, "violations": _INT},
        }},
        # only when there was no traffic to judge: why (the report does not pass, unless --allow-empty)
        "nothing_judged": _STR,
        # only when the proxy stood in the middle: what it changed, and what that made a side see
        "interventions": _INTERVENTIONS,
        # only with --group-by: the fleet tables (docs/fleet.md), one per key set
        "fleet": _FLEET,
        # only when some input could not be read: the report covers the others
        "unreadable": {"type": "array", "minItems": 1, "items": {
            "type": "object", "required": ["file", "error"], "additionalProperties": False,
            "properties": {"file": _STR, "error": _STR},
        }},
    },
}
