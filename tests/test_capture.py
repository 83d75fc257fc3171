"""``whiztap capture``: pcap/pcapng import with real reassembly, live capture,
and the Scapy layer."""

from __future__ import annotations

import asyncio
import os
import shutil
import signal
import subprocess

import pytest
from scapy.layers.inet import IP, TCP
from scapy.layers.l2 import Ether
from scapy.utils import PcapNgWriter, PcapWriter

from whiztap.sniffer.record.capture import CaptureError, CaptureSettings, import_pcap
from whiztap.sniffer.sim.client import Client
from whiztap.sniffer.record.scapy_layer import Progwhiz, bind
from whiztap.sniffer.sim.simulator import Simulator
from tests.cli_support import WHIZTAP, run_cli, start_process
from tests.record_support import LOCAL, WAIT, frame_items, on_channels, read_all, recording, streams

CLIENT, SERVER = ("10.1.1.2", 40000), ("10.1.1.9", 5000)
ISN_C, ISN_S = 1000, 9000


def _packet(src, dst, seq, ack, flags, payload=b"", t=0.0):
    p = Ether() / IP(src=src[0], dst=dst[0]) / TCP(sport=src[1], dport=dst[1], seq=seq % (1 << 32),
                                                   ack=ack % (1 << 32), flags=flags) / payload
    p.time = t
    return p


def _session(c2s_segments, s2c_segments, isn_c=ISN_C, isn_s=ISN_S):
    """Packets of one connection: handshake, the given (offset, bytes) segments
    in the given order, then FINs.  Offsets are stream offsets."""
    t = [1_700_000_000.0]

    def tick() -> float:
        t[0] += 0.001
        return t[0]

    pkts = [_packet(CLIENT, SERVER, isn_c, 0, "S", t=tick()),
            _packet(SERVER, CLIENT, isn_s, isn_c + 1, "SA", t=tick()),
            _packet(CLIENT, SERVER, isn_c + 1, isn_s + 1, "A", t=tick())]
    for (off, data), (soff, sdata) in zip(c2s_segments, s2c_segments):
        if data is not None:
            pkts.append(_packet(CLIENT, SERVER, isn_c + 1 + off, isn_s + 1, "PA", data, t=tick()))
        if sdata is not None:
            pkts.append(_packet(SERVER, CLIENT, isn_s + 1 + soff, isn_c + 1, "PA", sdata, t=tick()))
    c_end = max(o + len(d) for o, d in c2s_segments if d is not None)
    s_end = max(o + len(d) for o, d in s2c_segments if d is not None)
    pkts += [_packet(CLIENT, SERVER, isn_c + 1 + c_end, isn_s + 1 + s_end, "FA", t=tick()),
             _packet(SERVER, CLIENT, isn_s + 1 + s_end, isn_c + 2 + c_end, "FA", t=tick()),
             _packet(CLIENT, SERVER, isn_c + 2 + c_end, isn_s + 2 + s_end, "A", t=tick())]
    return pkts


def _write(path, pkts, ng=False) -> str:
    writer = (PcapNgWriter if ng else PcapWriter)(str(path))
    for p in pkts:
        writer.write(p)
    writer.close()
    return str(path)


C2S = b"rr1-24--0--0-ss1rr1-12--0--0-ss1rr1-3--0--2-ss1"
S2C = b"sr1-\x03200200000-ss1cr1-12--431--0-ss1cr1-3--400--0-ss1"


@pytest.mark.parametrize("ng", [False, True], ids=["pcap", "pcapng"])
def test_retransmissions_reordering_and_duplicates_reassemble_exactly(tmp_path, ng):
    # each list is in capture order: holes filled late, a retransmission, overlaps
    c = [(0, C2S[:16]), (32, C2S[32:]), (16, C2S[16:32]), (16, C2S[16:32])]
    s = [(0, S2C[:10]), (20, S2C[20:]), (10, S2C[10:20]), (5, S2C[5:25])]
    pcap = _write(tmp_path / ("in.pcapng" if ng else "in.pcap"), _session(c, s), ng)
    out = tmp_path / "out.mcap"
    summary = import_pcap(pcap, CaptureSettings(5000, str(out)))
    assert summary["connections"] == 1
    assert streams(str(out)) == {(1, "c2s"): C2S, (1, "s2c"): S2C}
    by_topic = read_all(str(out))
    assert [e["event"] for e in by_topic["/tcp/events"] if e["conn"] == 1] == [
        "opened", "upstream_connected", "half_closed", "half_closed", "closed"]
    assert not any(e["event"] == "gap" for e in by_topic["/tcp/events"])
    assert [v["value"] for v in by_topic["/sensors/12"]] == [431]
    assert [v["position"] for v in by_topic["/servos/3"]] == [100.0]
    opened = by_topic["/tcp/events"][1]
    assert (opened["client"], opened["upstream"]) == ("10.1.1.2:40000", "10.1.1.9:5000")


def test_a_segment_listed_after_the_ack_and_fin_that_followed_it_is_no_gap(tmp_path):
    """A capture taken on several CPUs can list a packet after the packets that
    answered it on the wire: here the client's last data comes after its own
    FIN and after the server's ACK of it."""
    c = [(0, C2S[:16]), (16, C2S[16:])]
    s = [(0, S2C[:5]), (5, S2C[5:])]
    syn, syn_ack, ack, c0, s0, c1, s1, c_fin, s_fin, last_ack = _session(c, s)
    pkts = [syn, syn_ack, ack, c0, s0, s1, c_fin, s_fin, c1, last_ack]
    out = tmp_path / "late.mcap"
    import_pcap(_write(tmp_path / "late.pcap", pkts), CaptureSettings(5000, str(out)))
    assert streams(str(out)) == {(1, "c2s"): C2S, (1, "s2c"): S2C}
    events = read_all(str(out))["/tcp/events"]
    assert not any(e["event"] == "gap" for e in events)
    assert [(e["event"], e.get("by")) for e in events if e["conn"] == 1][-1] == ("closed", "client")


def test_an_ack_beyond_a_fin_the_stream_reached_is_no_gap_after_the_close():
    """The client acknowledges server bytes far past the server's FIN (a
    confused capture); the server's FIN is reached, so nothing is owed: no event
    may follow the connection's close (the recorder knows it no more)."""
    from whiztap.sniffer.record.tcpreasm import ACK, FIN, SYN, Reassembler, Segment

    events: list = []

    class Consumer:
        def receive(self, event) -> None:
            events.append(event)

    r = Reassembler(5000, Consumer())
    for t, (src, dst, seq, ack, flags, payload) in enumerate([
            (CLIENT, SERVER, ISN_C, 0, SYN, b""), (SERVER, CLIENT, ISN_S, ISN_C + 1, SYN | ACK, b""),
            (CLIENT, SERVER, ISN_C + 1, ISN_S + 1, ACK, b""),
            (SERVER, CLIENT, ISN_S + 1, ISN_C + 1, ACK, b"sr1-"),
            (CLIENT, SERVER, ISN_C + 1, ISN_S + 10_000, ACK, b""),  # beyond anything the server sent
            (SERVER, CLIENT, ISN_S + 5, ISN_C + 1, FIN | ACK, b""),
            (CLIENT, SERVER, ISN_C + 9, ISN_S + 6, FIN | ACK, b"")]):  # 8 client bytes never seen
        r.segment(Segment(t, src, dst, seq, ack, flags, payload))
    r.finish(100)
    kinds = [type(e).__name__ for e in events]
    assert kinds[-1] == "Closed" and kinds.count("Closed") == 1
    assert [(type(e).__name__, e.direction.value) for e in events if type(e).__name__ == "Gap"] == [("Gap", "c2s")]


def test_missing_bytes_are_a_gap_never_zeros(tmp_path):
    c = [(0, C2S[:16]), (32, C2S[32:]), (16, None)]  # the middle frame never captured
    s = [(0, S2C[:5]), (5, S2C[5:]), (0, None)]
    pkts = _session(c, s, isn_c=(1 << 32) - 20)  # and sequence numbers wrap around
    pcap = _write(tmp_path / "gap.pcap", pkts)
    out = tmp_path / "gap.mcap"
    import_pcap(pcap, CaptureSettings(5000, str(out)))
    from tests.record_support import rebuild_streams

    segments = rebuild_streams(str(out))[(1, "c2s")]
    assert [(seg.offset, seg.data) for seg in segments] == [(0, C2S[:16]), (32, C2S[32:])]
    gaps = [e for e in read_all(str(out))["/tcp/events"] if e["event"] == "gap"]
    assert [(g["dir"], g["offset"], g["length"]) for g in gaps] == [("c2s", 16, 16)]
    frames = read_all(str(out))["/frames"]
    assert b"\x00" not in b"".join(raw for _, raw in frame_items(frames, 1, "c2s"))


def test_bad_input_is_a_clear_error(tmp_path):
    junk = tmp_path / "junk.pcap"
    junk.write_bytes(b"definitely not a capture file")
    with pytest.raises(CaptureError, match="not a pcap or pcapng file"):
        import_pcap(str(junk), CaptureSettings(5000, str(tmp_path / "x.mcap")))
    with pytest.raises(CaptureError, match="No such file"):
        import_pcap(str(tmp_path / "missing.pcap"), CaptureSettings(5000, str(tmp_path / "x.mcap")))


def test_the_command_keeps_an_existing_recording_unless_forced(tmp_path):
    pcap = _write(tmp_path / "s.pcap", _session([(0, C2S)], [(0, S2C)]))
    out = tmp_path / "s.mcap"
    out.write_bytes(b"an earlier recording")
    command = ["capture", "--pcap", pcap, "--port", "5000", "-o", out, "-q"]
    refused = run_cli(*command)
    assert refused.returncode == 2 and f"{out} exists; use --force" in refused.stderr
    assert out.read_bytes() == b"an earlier recording"
    forced = run_cli(*command, "--force")
    assert forced.returncode == 0, forced.stderr
    assert streams(str(out)) == {(1, "c2s"): C2S, (1, "s2c"): S2C}


@pytest.mark.slow
def test_the_import_says_how_far_into_the_file_it_is(tmp_path):
    frames = [b"rr1-%d--0--0-ss1" % (12 + i % 10) for i in range(1100)]  # 2,200 data packets and more
    answers = [f.replace(b"rr1-", b"cr1-") for f in frames]
    offsets = [16 * i for i in range(len(frames))]
    pcap = _write(tmp_path / "long.pcap", _session(list(zip(offsets, frames)), list(zip(offsets, answers))))
    positions: list[int] = []
    import_pcap(pcap, CaptureSettings(5000, str(tmp_path / "long.mcap")), progress=positions.append)
    assert len(positions) >= 2 and positions == sorted(positions)  # now and then, never backwards
    assert positions[-1] == os.path.getsize(pcap)  # and the whole file at the end
    assert streams(str(tmp_path / "long.mcap"))[(1, "c2s")] == b"".join(frames)


def test_scapy_layer_dissects_both_directions():
    bind(5000)
    request = IP(bytes(IP() / TCP(sport=40000, dport=5000) / b"rr1-3--0--2-ss1"))
    reply = IP(bytes(IP() / TCP(sport=5000, dport=40000) / b"cr1-3--400--0-ss1cr1-4--1--0-ss1"))
    assert request[Progwhiz].describe_items() == ["Servo Position Request ch 3"]
    assert [i.raw for i in reply[Progwhiz].items()] == [b"cr1-3--400--0-ss1", b"cr1-4--1--0-ss1"]
    assert "Progwhiz Response ch 3 data 400" in reply.summary()


# -- real traffic ------------------------------------------------------------------------------------------


async def _session_through_proxy(path, sim_port: int) -> None:
    async with recording(sim_port, path) as rec:
        async with await Client.connect(LOCAL, rec.proxy.port, password="progwhiz") as client:
            await client.fetch_configuration()
            for ch in (12, 13, 0, 1):
                await (client.sensor(ch) if ch >= 12 else client.servo_position(ch))
            await client.normal_send(2, 700)
            await client.fetch_camera_image()


def _payload_bytes_seen(pcap, port: int, partial: bool = False) -> dict[str, int]:
    """Per direction of the capture's one connection to ``port``, how many stream
    bytes its packets cover (read with Scapy, not with the code under test):
    tcpdump itself sometimes misses packets when the machine is busy.  With
    ``partial``, a file tcpdump has not written its header to yet covers none."""
    from scapy.error import Scapy_Exception
    from scapy.utils import rdpcap

    if partial:
        try:
            return _payload_bytes_seen(pcap, port)
        except Scapy_Exception:
            return {}

    spans: dict[str, set[int]] = {"c2s": set(), "s2c": set()}
    first: dict[str, int] = {}
    for packet in rdpcap(str(pcap)):
        if TCP not in packet:
            continue
        tcp = packet[TCP]
        direction = "c2s" if tcp.dport == port else "s2c"
        if tcp.flags & 0x02:  # SYN
            first[direction] = (tcp.seq + 1) % (1 << 32)
        elif direction in first and tcp.payload:
            start = (tcp.seq - first[direction]) % (1 << 32)
            spans[direction].update(range(start, start + len(tcp.payload)))
    return {d: len(covered) for d, covered in spans.items()}


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("tcpdump") is None,
                    reason="tcpdump is not installed (make test installs it with apt-get as root)")
@pytest.mark.skipif(os.geteuid() != 0, reason="tcpdump on lo needs root")
async def test_a_tcpdump_capture_imports_to_the_frames_the_proxy_recorded(tmp_path):
    for attempt in range(5):  # a capture that tcpdump itself missed packets of is taken again
        pcap, proxy_rec, imported = (tmp_path / f"{name}-{attempt}.{ext}" for name, ext in
                                     (("lo", "pcap"), ("proxy", "mcap"), ("imported", "mcap")))
        async with Simulator(port=0, mode="winsock", password="progwhiz", seed=5) as sim:
            port = sim.port
            dump = await asyncio.create_subprocess_exec(
                # immediate mode: else packets wait in the kernel ring for a timeout
                # that SIGINT may cut short, and the file comes out empty
                "tcpdump", "-i", "lo", "--immediate-mode", "-U", "-s", "0", "-w", str(pcap), f"tcp port {port}",
                stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE)
            line = await asyncio.wait_for(dump.stderr.readline(), WAIT)  # "listening on lo, ..."
            assert b"listening on" in line, line
            await _session_through_proxy(proxy_rec, port)
            recorded = streams(str(proxy_rec))
            conn = max(c for c, _ in recorded)
            wanted = {d: len(recorded[(conn, d)]) for d in ("c2s", "s2c")}
            # SIGINT ends tcpdump at once, dropping what the kernel still holds for
            # it: stop it once its file holds every byte the proxy recorded (on a
            # loaded machine tcpdump may write them seconds later), or after 5 s,
            # when it has missed some and the capture is taken again
            for _ in range(50):
                await asyncio.sleep(0.1)
                if _payload_bytes_seen(pcap, port, partial=True) == wanted:
                    break
            dump.send_signal(signal.SIGINT)
            await asyncio.wait_for(dump.wait(), WAIT)
        if _payload_bytes_seen(pcap, port) == wanted:
            break
    else:
        pytest.fail("tcpdump missed packets in five captures in a row: the machine is too busy to test this")
    import_pcap(str(pcap), CaptureSettings(port, str(imported)))
    # the proxy's upstream leg is what tcpdump saw: same streams, same frames
    assert streams(str(imported)) == recorded
    a, b = read_all(str(imported)), read_all(str(proxy_rec))
    for direction in ("c2s", "s2c"):
        assert frame_items(a["/frames"], 1, direction) == frame_items(b["/frames"], 1, direction)
    assert [m["value"] for m in on_channels(a, "/sensors")] == [m["value"] for m in on_channels(b, "/sensors")]
    assert len(a["/camera"]) == 1


@pytest.mark.slow
@pytest.mark.skipif(os.geteuid() != 0, reason="live capture needs root or CAP_NET_RAW")
async def test_live_capture_on_loopback_until_ctrl_c(tmp_path):
    out = tmp_path / "live.mcap"
    async with Simulator(port=0, mode="vpn", seed=2, camera=False) as sim:
        proc = await start_process("capture", "--iface", "lo", "--port", sim.port, "-o", out)
        assert b"capturing tcp port" in await asyncio.wait_for(proc.stdout.readline(), WAIT)
        async with await Client.connect(LOCAL, sim.port) as client:
            await client.fetch_configuration()
            value = await client.sensor(15)
        proc.send_signal(signal.SIGINT)  # it still records what the kernel queued before
        stdout, stderr = await asyncio.wait_for(proc.communicate(), WAIT)
    assert proc.returncode == 0, stderr
    assert b"captured 1 connection into" in stdout
    by_topic = read_all(str(out))
    assert [m["value"] for m in by_topic["/sensors/15"]] == [value]
    recorded = streams(str(out))
    assert recorded[(1, "c2s")] == b"rr1-24--0--0-ss1rr1-15--0--0-ss1"


@pytest.mark.slow
def test_live_capture_without_the_right_says_what_is_needed(tmp_path):
    command = [WHIZTAP, "capture", "--iface", "lo", "--port", "5000", "-o", str(tmp_path / "x.mcap")]
    if os.geteuid() == 0:
        if shutil.which("setpriv") is None:
            pytest.skip("running as root and setpriv (util-linux) is missing to drop the right")
        # Root without the one capability: still the same user, so it can read the
        # virtualenv wherever the repository was cloned (a private 0700 folder too).
        command = ["setpriv", "--bounding-set=-net_raw", "--inh-caps=-net_raw", *command]
    result = subprocess.run(command, capture_output=True, text=True, timeout=WAIT)
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr
    assert "needs root or the CAP_NET_RAW capability" in result.stderr
