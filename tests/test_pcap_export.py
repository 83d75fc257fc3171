"""``whiztap export --pcap``: recordings as TCP packets in pcapng, and back
through ``whiztap capture --pcap`` (with and without ``--port``) to the same
byte streams, read boundaries and times."""

from __future__ import annotations

import asyncio
import base64
import json
import os
import shutil
import signal
import subprocess
from collections import defaultdict
from itertools import pairwise
from pathlib import Path

import pytest
from scapy.layers.inet import IP, TCP
from scapy.utils import PcapWriter, rdpcap

from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.recording.format import TOPIC_EVENTS, TOPIC_READS
from whiztap.analyzer.recording.scan import RecordingScan, read_metadata
from whiztap.analyzer.recording.sets import find_one
from whiztap.analyzer.traffic import Closed, Data, Gap, HalfClosed, Opened, UpstreamConnected, UpstreamFailed
from whiztap.sniffer.record.capture import CaptureSettings, import_pcap
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.writer import RecordingFile
from whiztap.sniffer.wireshark.export import addresses, export_pcapng
from whiztap.sniffer.wireshark.pcapng import MAX_PAYLOAD
from whiztap.sniffer.sim.client import Client
from whiztap.sniffer.sim.simulator import Simulator
from tests.cli_support import WHIZTAP, run_cli, start_process
from tests.record_support import LOCAL, WAIT

SAMPLES = Path(__file__).parent.parent / "samples"
C, S = Direction.C2S, Direction.S2C
T0, MS = 1_700_000_000_000_000_000, 1_000_000
TSHARK = shutil.which("tshark")


def _reads(path: Path) -> dict[tuple[int, str], list[tuple[int, int, bytes]]]:
    """Each direction's reads as (time, stream offset, bytes): boundaries and times, not just bytes."""
    out: dict[tuple[int, str], list[tuple[int, int, bytes]]] = defaultdict(list)
    with open(path, "rb") as f:
        for _, _, m in RecordingScan(f, (TOPIC_READS,)).messages():
            out[(m["conn"], m["dir"])].append((m["t_ns"], m["offset"], base64.b64decode(m["data"])))
    return dict(out)


def _as_packets(reads: dict[tuple[int, str], list[tuple[int, int, bytes]]]) -> dict:
    """The reads as the export cuts them: one longer than a packet carries is several."""
    return {key: [(t, offset + i, data[i:i + MAX_PAYLOAD]) for t, offset, data in each
                  for i in range(0, len(data), MAX_PAYLOAD)] for key, each in reads.items()}


def _events(path: Path, *names: str) -> list[tuple]:
    with open(path, "rb") as f:
        return [tuple(m.get(k) for k in ("conn", "event", "dir", "offset", "length", "client", "upstream"))
                for _, _, m in RecordingScan(f, (TOPIC_EVENTS,)).messages() if m["event"] in names]


def _export(recording: Path, out: Path) -> Path:
    with open(out, "wb") as f:
        export_pcapng(find_one([str(recording)]), f)
    return out


def _capture_back(pcap: Path, out: Path, port: int | None, keep_secrets: bool = True) -> Path:
    import_pcap(str(pcap), CaptureSettings(port, str(out), keep_secrets=keep_secrets))
    return out


def _record(path: Path, events: list, keep_secrets: bool = True) -> Path:
    """A recording of ``events`` written by the real recorder."""
    recorder = Recorder(RecordingFile(str(path), {"source": "test"}), keep_secrets=keep_secrets)
    recorder.start(T0)
    for event in events:
        recorder.receive(event)
    recorder.stop(events[-1].t_ns + MS)
    return path


def _session(conn: int = 1, t: int = T0, client: str = "192.0.2.7:40001", upstream: str = "192.0.2.1:5000") -> list:
    return [Opened(conn, t + MS, client, upstream), UpstreamConnected(conn, t + 2 * MS),
            Data(conn, C, t + 3 * MS, b"rr1-24--0--0-ss1"), Data(conn, S, t + 4 * MS, b"sr1-\x01200-ss1"),
            Data(conn, C, t + 5 * MS, b"rr1-0--0--0-ss1"), Data(conn, S, t + 6 * MS, b"cr1-0--431--0-ss1"),
            HalfClosed(conn, t + 7 * MS, C), Closed(conn, t + 8 * MS, "client", "closed")]


@pytest.mark.parametrize("port_given", [True, False], ids=["port", "by-content"])
@pytest.mark.parametrize("sample", ["clean-winsock", "vpn", "failed-password", "violations"])
def test_every_sample_comes_back_the_same_through_pcapng(tmp_path, sample, port_given):
    recording = SAMPLES / f"{sample}.mcap"
    meta = read_metadata(str(recording))
    port = int(meta["upstream"].rpartition(":")[2]) if port_given else None
    back = _capture_back(_export(recording, tmp_path / "out.pcapng"), tmp_path / "back.mcap", port,
                         keep_secrets=meta["secrets"] == "kept")
    assert _reads(back) == _as_packets(_reads(recording))  # bytes, read boundaries and times, per connection
    assert _events(back, "opened") == _events(recording, "opened")  # the same addresses, in order


def test_the_commands_round_trip_a_recording(tmp_path):
    pcap, back = tmp_path / "clean.pcapng", tmp_path / "back.mcap"
    done = run_cli("export", "--pcap", pcap, SAMPLES / "clean-winsock.mcap")
    assert done.returncode == 0, done.stderr
    assert f"into {pcap}" in done.stdout and "exported 1 connection, " in done.stdout
    captured = run_cli("capture", "--pcap", pcap, "-o", back)
    assert captured.returncode == 0, captured.stderr
    assert _reads(back) == _reads(SAMPLES / "clean-winsock.mcap")
    assert read_metadata(str(back))["server_port"] == ""  # found by content


def test_gaps_are_jumps_in_the_sequence_numbers_and_come_back_as_gaps(tmp_path):
    events = _session()
    events[4:4] = [Gap(1, T0 + 5 * MS, C, 10), Data(1, C, T0 + 5 * MS, b"rr1-0--0--2-ss1")]
    events[-2:-2] = [Gap(1, T0 + 7 * MS, S, 7)]  # missing at the end of a stream, before its close
    recording = _record(tmp_path / "gaps.mcap", events)
    pcap = _export(recording, tmp_path / "gaps.pcapng")
    back = _capture_back(pcap, tmp_path / "back.mcap", None)
    # the bytes after a hole come back when the capture gives up on it (at a FIN
    # here), so their times are that one's; where each byte is does not change
    assert {k: [r[1:] for r in v] for k, v in _reads(back).items()} == {
        k: [r[1:] for r in v] for k, v in _reads(recording).items()}
    gaps = [g[:5] for g in _events(back, "gap")]
    assert sorted(gaps) == sorted(g[:5] for g in _events(recording, "gap")) == [
        (1, "gap", "c2s", 16, 10), (1, "gap", "s2c", 29, 7)]
    if TSHARK:
        lost = subprocess.run([TSHARK, "-r", str(pcap), "-Y", "tcp.analysis.lost_segment", "-T", "fields",
                               "-e", "tcp.seq"], capture_output=True, text=True, timeout=60)
        assert lost.stdout.split() == ["27", "37"]  # "previous segment not captured": c2s data, s2c FIN


@pytest.mark.slow
def test_a_read_longer_than_a_packet_is_several_segments(tmp_path):
    big = b"sr1-25--" + bytes(range(1, 21)) * 10_000  # 200,008 bytes in one read
    events = _session()
    events[4:4] = [Data(1, C, T0 + 5 * MS, big)]
    recording = _record(tmp_path / "big.mcap", events)
    pcap = _export(recording, tmp_path / "big.pcapng")
    sizes = [len(p[TCP].payload) for p in rdpcap(str(pcap)) if len(p[TCP].payload) > 1000]
    assert sizes == [MAX_PAYLOAD] * 3 + [len(big) - 3 * MAX_PAYLOAD]
    back = _capture_back(pcap, tmp_path / "back.mcap", 5000)
    reads = _reads(back)[(1, "c2s")]
    assert b"".join(r[2] for r in reads) == b"rr1-24--0--0-ss1" + big + b"rr1-0--0--0-ss1"
    assert [len(r[2]) for r in reads][1:5] == sizes  # the one read is as many as the packets


def test_refused_reset_and_ipv6_connections_come_back_as_they_were(tmp_path):
    events = [Opened(1, T0 + MS, "[2001:db8::7]:40001", "[2001:db8::1]:5000"),
              UpstreamFailed(1, T0 + 2 * MS, "refused"), Closed(1, T0 + 3 * MS, "server", "reset (refused)")]
    events += _session(2, T0 + 10 * MS, "[2001:db8::7]:40002", "[2001:db8::1]:5000")[:-2]
    events += [Closed(2, T0 + 30 * MS, "server", "reset (by peer)")]
    recording = _record(tmp_path / "ends.mcap", events)
    back = _capture_back(_export(recording, tmp_path / "ends.pcapng"), tmp_path / "back.mcap", 5000)
    assert _reads(back) == _reads(recording)
    assert _events(back, "opened") == _events(recording, "opened")
    ends = [e[:2] for e in _events(back, "upstream_failed", "closed")]
    assert ends == [(1, "upstream_failed"), (1, "closed"), (2, "closed")]


def test_addresses_fall_back_to_stand_ins_of_the_servers_family():
    client, server = addresses(3, "127.0.0.1:40000", "127.0.0.1:5000")
    assert (client.port, server.port, client.version) == (40000, 5000, 4)
    client, server = addresses(3, "", "")  # a recording that does not say
    assert (bytes(client.address), client.port, bytes(server.address), server.port) == (
        bytes([10, 0, 0, 2]), 1026, bytes([10, 0, 0, 1]), 5000)
    client, server = addresses(1, "[::1]:40000", "10.9.8.7:6000")  # one conversation has one family
    assert (client.version, bytes(client.address), server.port) == (4, bytes([10, 0, 0, 2]), 6000)


def test_a_masked_password_stays_masked_and_says_so(tmp_path):
    events = [Opened(1, T0 + MS, "192.0.2.7:40001", "192.0.2.1:5000"), UpstreamConnected(1, T0 + 2 * MS),
              Data(1, S, T0 + 3 * MS, b"sendchkpass"), Data(1, C, T0 + 4 * MS, b"hunter2\r\n"),
              Data(1, S, T0 + 5 * MS, b"readytogo"), Closed(1, T0 + 6 * MS, "client", "closed")]
    recording = _record(tmp_path / "secret.mcap", events, keep_secrets=False)
    pcap = _export(recording, tmp_path / "secret.pcapng").read_bytes()
    assert b"hunter2" not in pcap and b"*******\r\n" in pcap
    assert b"a password, masked" in pcap  # a packet comment Wireshark shows


def test_the_export_command_writes_to_standard_output_and_refuses_what_it_should(tmp_path):
    sample = str(SAMPLES / "vpn.mcap")
    # a process of its own: binary on a real pipe
    piped = subprocess.run([WHIZTAP, "export", "--pcap", "-", sample], capture_output=True, timeout=60)
    assert piped.returncode == 0 and piped.stdout.startswith(b"\x0a\x0d\x0d\x0a")  # a pcapng section
    assert piped.stdout == _export(SAMPLES / "vpn.mcap", tmp_path / "vpn.pcapng").read_bytes()
    taken = tmp_path / "taken.pcapng"
    taken.write_bytes(b"keep me")
    for args, says in (([str(taken), sample], "exists; use --force"),
                       ([str(tmp_path / "x.pcapng"), str(tmp_path / "missing.mcap")], "missing.mcap"),
                       ([sample, sample], "an input")):
        refused = run_cli("export", "--pcap", *args)
        assert refused.returncode == 2 and refused.stderr.count("\n") == 1 and says in refused.stderr, refused.stderr
    assert taken.read_bytes() == b"keep me"
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes((SAMPLES / "vpn.mcap").read_bytes()[:5000])
    out = tmp_path / "damaged.pcapng"
    failed = run_cli("export", "--pcap", out, damaged)
    assert failed.returncode == 2 and failed.stderr.count("\n") == 1 and "recover" in failed.stderr
    assert not out.exists()  # no half-written file left behind
    helped = run_cli("export", "--help")
    assert helped.returncode == 0 and "--pcap OUT.pcapng" in helped.stdout


# -- capture without --port ---------------------------------------------------------------------


def _conversation(client, server, c2s: bytes, s2c: bytes, t: float, syn: bool = True):
    """One TCP conversation's packets: a handshake (if ``syn``), the server's
    bytes, the client's, and FINs."""
    def packet(src, dst, seq, ack, flags, payload=b""):
        p = IP(src=src[0], dst=dst[0]) / TCP(sport=src[1], dport=dst[1], seq=seq, ack=ack, flags=flags) / payload
        p.time = t + len(out) * 0.001
        return p

    out: list = []
    if syn:
        out += [packet(client, server, 99, 0, "S"), packet(server, client, 499, 100, "SA"),
                packet(client, server, 100, 500, "A")]
    for p in ([packet(server, client, 500, 100, "PA", s2c)] if s2c else []) + [
            packet(client, server, 100, 500 + len(s2c), "PA", c2s)]:
        out.append(p)
    out += [packet(client, server, 100 + len(c2s), 500 + len(s2c), "FA"),
            packet(server, client, 500 + len(s2c), 101 + len(c2s), "FA")]
    return out


def test_capture_without_a_port_records_only_the_progwhiz_conversations(tmp_path):
    pcap = tmp_path / "mixed.pcap"
    writer = PcapWriter(str(pcap), linktype=101)
    for p in (_conversation(("192.0.2.7", 40001), ("192.0.2.1", 80), b"GET / HTTP/1.1\r\n\r\n", b"", 1.0)
              + _conversation(("192.0.2.7", 40002), ("192.0.2.1", 7777), b"secret\r\n", b"sendchkpass", 2.0,
                              syn=False)  # joined mid-stream: the content says which side serves
              + _conversation(("192.0.2.7", 40003), ("192.0.2.1", 9000), b"rr1-24--0--0-ss1", b"", 3.0)
              + _conversation(("192.0.2.7", 40004), ("192.0.2.1", 443), b"\x16\x03\x01", b"\x16\x03\x03", 4.0)):
        writer.write(p)
    writer.close()
    back = _capture_back(pcap, tmp_path / "found.mcap", None)
    assert [(e[0], e[5], e[6]) for e in _events(back, "opened")] == [
        (1, "192.0.2.7:40002", "192.0.2.1:7777"), (2, "192.0.2.7:40003", "192.0.2.1:9000")]
    assert {k: b"".join(r[2] for r in v) for k, v in _reads(back).items()} == {
        (1, "s2c"): b"sendchkpass", (1, "c2s"): b"secret\r\n", (2, "c2s"): b"rr1-24--0--0-ss1"}


@pytest.mark.skipif(os.geteuid() != 0, reason="live capture needs root or CAP_NET_RAW")
async def test_a_live_capture_without_a_port_finds_the_robot(tmp_path):
    out = tmp_path / "live.mcap"
    async with Simulator(port=0, mode="vpn", seed=2, camera=False) as sim:
        port = sim.port
        proc = await start_process("capture", "--iface", "lo", "-o", out)
        said = await asyncio.wait_for(proc.stdout.readline(), WAIT)
        assert b"capturing Progwhiz conversations on any TCP port" in said
        async with await Client.connect(LOCAL, port) as client:
            await client.fetch_configuration()
            await client.sensor(15)
        proc.send_signal(signal.SIGINT)
        _, stderr = await asyncio.wait_for(proc.communicate(), WAIT)
    assert proc.returncode == 0, stderr
    # the robot's port, found by what it said; any other Progwhiz traffic on lo
    # at the time (another test run on this machine) is recorded too, rightly
    [opened] = [e for e in _events(out, "opened") if e[6] == f"127.0.0.1:{port}"]
    assert b"".join(r[2] for r in _reads(out)[(opened[0], "c2s")]) == b"rr1-24--0--0-ss1rr1-15--0--0-ss1"


def test_export_and_the_shared_reader_agree_on_offsets_and_masks_of_a_split_masked_recording(tmp_path):
    """The one reader of recording sets gives each read the stream offset and
    masked flag the file says (read here with the mcap package's own reader),
    across parts and a missing one; the export's sequence numbers and
    password comments are those."""
    from mcap.reader import make_reader

    from whiztap.analyzer.recording.sets import scan_set

    file = RecordingFile(str(tmp_path / "s.mcap"), {"session_id": "s", "split_duration": "0.01"},
                         split_duration_ns=10 * MS)
    rec = Recorder(file, keep_secrets=False)
    rec.start(T0)
    t = T0 + MS
    for event in [Opened(1, t, "192.0.2.7:40001", "192.0.2.1:5000"), UpstreamConnected(1, t),
                  Data(1, S, t, b"sendchkpass"), Data(1, C, t, b"hunter2\r\n"), Data(1, S, t, b"readytogo")]:
        rec.receive(event)
    for n in range(3):  # each part has a request, its answer and more; the middle part goes missing below
        t += 20 * MS
        rec.tick(t)
        rec.receive(Data(1, C, t, b"rr1-%d--0--0-ss1" % n))
        rec.receive(Data(1, S, t + MS, b"cr1-%d--43--0-ss1" % n))
    rec.receive(Closed(1, t + 2 * MS, "client", "closed"))
    files = rec.stop(t + 3 * MS).files
    assert len(files) == 4
    os.unlink(files[2])
    recording = find_one([files[0]])
    assert recording.missing == (3,)

    expected = []
    for part in recording.parts:
        with open(part, "rb") as f:
            for _, channel, message in make_reader(f).iter_messages(topics=[TOPIC_READS]):
                assert channel.topic == TOPIC_READS
                m = json.loads(message.data)
                expected.append((m["conn"], Direction(m["dir"]), m["offset"], bool(m.get("redacted"))))
    got = [(e.conn, e.direction, e.offset, e.masked) for e in scan_set(recording) if type(e) is Data]
    assert got == expected
    assert any(masked for *_, masked in got)  # the password, masked
    c2s = [offset for _, d, offset, _ in got if d is C]
    assert any(b - a > 15 for a, b in pairwise(c2s))  # the missing part: a jump

    packets = [p for p in rdpcap(str(_export(Path(files[0]), tmp_path / "s.pcapng"))) if TCP in p]
    syn = {(p[IP].src == "192.0.2.7"): p[TCP].seq for p in packets if p[TCP].flags & 0x02}
    segments = [(C if p[IP].src == "192.0.2.7" else S, p[TCP].seq - syn[p[IP].src == "192.0.2.7"] - 1,
                 b"password, masked" in (p.comment or b"")) for p in packets if len(p[TCP].payload)]
    assert segments == [(d, offset, masked) for _, d, offset, masked in got]
