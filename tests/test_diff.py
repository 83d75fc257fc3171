"""``whiztap diff``: recordings made by the real simulator through the real
recording proxy, with and without planted bugs, compared exchange by exchange;
the pairing's symmetry checked by hypothesis over a real recording's exchanges."""

from __future__ import annotations

import asyncio
import dataclasses
import json
from collections import Counter
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from whiztap.analyzer.analysis.diff import Difference, Kind, diff_sessions
from whiztap.analyzer.analysis.exchanges import RecordedConnection, load_exchanges
from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.codec import encode
from whiztap.sniffer.sim.faults import FaultConfig
from whiztap.sniffer.sim.simulator import Simulator

from tests.cli_support import run_cli
from tests.record_support import LOCAL, WAIT, recording
from tests.replay_support import record as record_winsock
from tests.replay_support import until_closed

FROZEN = 42_000_000_000  # a stopped clock: the same readings every run of one seed
REQUESTS = b"".join([*(encode(m.SensorRequest(ch)) for ch in (12, 13, 12, 14, 15, 12)),
                     encode(m.ServoPositionRequest(0)), encode(m.NormalSend(0, 1500))])


async def _session(port: int) -> None:
    """A VPN client: the configuration, then every request in one write, and every answer read to the end."""
    reader, writer = await asyncio.open_connection(LOCAL, port)
    async with asyncio.timeout(WAIT):
        writer.write(encode(m.FetchConfiguration()))
        got = b""
        while not got.endswith(b"-ss1"):
            got += await reader.read(65536) or b"-ss1"
        writer.write(REQUESTS)
        writer.write_eof()
        while await reader.read(65536):
            pass
    writer.close()


async def _record(path: Path, seed: int, bugs: tuple[str, ...] = (), faults: FaultConfig = FaultConfig()) -> None:
    async with Simulator(mode="vpn", seed=seed, clock=lambda: FROZEN, bugs=bugs, faults=faults) as sim, \
            recording(sim.port, str(path)) as rec:
        await _session(rec.proxy.port)
        await until_closed(sim)
        await rec.stop()


@pytest.fixture(scope="module")
def made(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """One recording per variant, made once for the module."""
    folder = tmp_path_factory.mktemp("diff")
    variants = {"clean": (1, ()), "again": (1, ()), "seed2": (2, ()), "out-of-range": (1, ("out-of-range",)),
                "wrong-channel": (1, ("wrong-channel",)), "drop-nth": (1, ("drop-nth",))}
    paths = {name: folder / f"{name}.mcap" for name in [*variants, "slow", "winsock"]}

    async def make() -> None:
        for name, (seed, bugs) in variants.items():
            await _record(paths[name], seed, bugs)
        await _record(paths["slow"], 1, faults=FaultConfig(latency_ms=300))
        await record_winsock(paths["winsock"])

    asyncio.run(make())
    return paths


def diff(a: Path, b: Path, *more: str) -> tuple[int, dict]:
    ran = run_cli("diff", a, b, "--format", "json", *more)
    assert ran.returncode in (0, 1), ran.stderr
    return ran.returncode, json.loads(ran.stdout)


def test_the_same_session_twice_is_equal(made):
    code, out = diff(made["clean"], made["again"])
    assert code == 0 and out["equal"] and out["differences"] == []
    assert out["exchanges"] == 9  # the configuration and the eight requests


def test_another_seed_differs_in_the_readings_only_and_nobody_is_at_fault(made):
    code, out = diff(made["clean"], made["seed2"])
    assert code == 1
    assert {d["kind"] for d in out["differences"]} == {"value"}
    assert all("sensor_value" in d["what"] and d["at_fault"] == "neither" for d in out["differences"])
    assert {d["exchange"] for d in out["differences"]} >= {"Sensor Request #3 on channel 12"}


def test_an_out_of_range_server_is_blamed_in_b(made):
    _, out = diff(made["clean"], made["out-of-range"])
    sensors = [d for d in out["differences"] if d["exchange"].startswith("Sensor Request")]
    assert len(sensors) == 6 and all(d["kind"] == "value" and d["at_fault"] == "B" for d in sensors)
    assert {(b["recording"], b["side"], b["rule"]) for d in sensors for b in d["breaches"]} == \
        {("B", "server", "PW-RANGE-SENSOR")}


@pytest.mark.parametrize("bug, missing", [("wrong-channel", 4), ("drop-nth", 1)])
def test_a_server_that_leaves_requests_unanswered_misses_them_in_b(made, bug, missing):
    _, out = diff(made["clean"], made[bug])
    gone = [d for d in out["differences"] if d["kind"] == "missing"]
    assert len(gone) == missing
    assert all(d["what"] == "the answer" and d["b"] == "no answer" and d["at_fault"] == "B" for d in gone)
    assert all(("B", "PW-PAIR-UNANSWERED") in {(b["recording"], b["rule"]) for b in d["breaches"]} for d in gone)
    # and the other way round, the same answers are extra in B
    _, back = diff(made[bug], made["clean"])
    assert Counter(d["kind"] for d in back["differences"]) == \
        Counter({"missing": "extra", "extra": "missing"}.get(d["kind"], d["kind"]) for d in out["differences"])


def test_latency_beyond_the_tolerance_is_a_timing_difference(made):
    code, out = diff(made["clean"], made["slow"], "--latency-tolerance", "100")
    assert code == 1 and out["counts"] == {"timing": 8}  # config + 7 answered; Normal Send has none
    code, out = diff(made["clean"], made["slow"], "--latency-tolerance", "100000")
    assert code == 0 and out["equal"]


def test_a_different_handshake_is_named(made):
    _, out = diff(made["clean"], made["winsock"])
    [hand] = [d for d in out["differences"] if d["kind"] == "handshake"]
    assert hand["a"].startswith("vpn") and hand["b"] == "winsock, password accepted"


def test_every_format_renders_to_a_file(made, tmp_path):
    for fmt, mark in (("text", "breaks the spec: B"), ("markdown", "| connection |"), ("html", "<table>"),
                      ("json", '"at_fault": "B"')):
        out = tmp_path / f"report.{fmt}"
        ran = run_cli("diff", made["clean"], made["out-of-range"], "--format", fmt, "-o", out)
        assert ran.returncode == 1 and ran.stdout == "", ran.stderr
        assert mark in out.read_text(), fmt
    assert run_cli("diff", made["clean"], made["again"], "-o", out).returncode == 2  # exists: --force


def test_unreadable_recordings_are_one_line_and_status_2(made, tmp_path):
    cut = tmp_path / "cut.mcap"
    data = made["clean"].read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    for a, b in ((made["clean"], tmp_path / "absent.mcap"), (cut, made["clean"])):
        ran = run_cli("diff", a, b)
        assert ran.returncode == 2 and ran.stdout == ""
        assert ran.stderr.count("\n") == 1 and "Traceback" not in ran.stderr, ran.stderr
    assert "whiztap recover" in run_cli("diff", cut, made["clean"]).stderr


# -- the pairing's symmetry, over a real recording's exchanges ----------------------------------------


@pytest.fixture(scope="module")
def connections(made) -> list[RecordedConnection]:
    return load_exchanges(made["drop-nth"]).connections + load_exchanges(made["seed2"]).connections


def _cut(connection: RecordedConnection, keep: list[bool], answered: list[bool]) -> RecordedConnection:
    """The connection with some of its items left out and some answers taken away."""
    items = [item if answer else dataclasses.replace(item, answer=None)
             for item, kept, answer in zip(connection.items, keep, answered, strict=False) if kept]
    return dataclasses.replace(connection, items=items)


SWAPPED = {Kind.MISSING: Kind.EXTRA, Kind.EXTRA: Kind.MISSING}


def _swapped(d: Difference) -> Difference:
    """The same difference seen from the other recording."""
    breaches = tuple(dataclasses.replace(b, recording="B" if b.recording == "A" else "A") for b in d.breaches)
    return dataclasses.replace(d, kind=SWAPPED.get(d.kind, d.kind), a=d.b, b=d.a, breaches=breaches)


def _unordered(differences: list[Difference]) -> Counter:
    # "what" quotes a changed field A -> B, so only the rest is compared across the swap
    return Counter((d.kind, d.connection, d.exchange, d.a, d.b, tuple(sorted(map(repr, d.breaches))))
                   for d in differences)


@settings(max_examples=40, deadline=None)
@given(data=st.data())
def test_a_recording_equals_itself_and_swapping_swaps_missing_and_extra(connections, data):
    def drawn() -> list[RecordedConnection]:
        chosen = data.draw(st.lists(st.sampled_from(range(len(connections))), max_size=3))
        return [_cut(connections[i], data.draw(st.lists(st.booleans(), min_size=12, max_size=12)),
                     data.draw(st.lists(st.booleans(), min_size=12, max_size=12))) for i in chosen]

    a, b = drawn(), drawn()
    assert diff_sessions(a, a).equal
    forth, back = diff_sessions(a, b).differences, diff_sessions(b, a).differences
    assert _unordered(back) == _unordered([_swapped(d) for d in forth])
    assert Counter(d.kind for d in back) == Counter(SWAPPED.get(d.kind, d.kind) for d in forth)


@settings(max_examples=30, deadline=None)
@given(cut=st.floats(0, 1), tail=st.binary(max_size=64))
def test_any_damaged_file_is_one_line_never_a_traceback(made, tmp_path_factory, cut, tail):
    """Bytes from outside: a recording cut anywhere and followed by anything."""
    data = made["clean"].read_bytes()
    damaged = tmp_path_factory.mktemp("damaged") / "b.mcap"
    damaged.write_bytes(data[: int(len(data) * cut)] + tail)
    ran = run_cli("diff", made["clean"], damaged)
    if ran.returncode == 2:
        assert ran.stdout == "" and ran.stderr.count("\n") == 1, ran.stderr
    else:  # a tail that leaves the file whole (cut at 1, nothing added) compares as usual
        assert ran.returncode in (0, 1), ran.stderr


def test_past_the_cap_differences_are_counted_not_kept(made):
    a, b = (load_exchanges(made[name]).connections for name in ("clean", "out-of-range"))
    result = diff_sessions(a, b, max_kept=2)
    assert len(result.differences) == 2 and result.total == 6 and result.counts() == {"value": 6}
    assert not result.equal
