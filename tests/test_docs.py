"""The protocol page lists every rule and every checksum candidate that exists."""

from pathlib import Path

from analyzer.checksum import CHECKSUM_RULES
from analyzer.rules import RULES

PROTOCOL = (Path(__file__).parent.parent / "docs" / "protocol.md").read_text()


def test_every_rule_is_documented_with_its_severity():
    for rule in RULES.values():
        assert f"| `{rule.id}` | {rule.severity} |" in PROTOCOL, rule.id


def test_every_checksum_rule_is_documented():
    for name in CHECKSUM_RULES:
        assert f"`{name}`" in PROTOCOL, name
