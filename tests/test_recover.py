"""``whiztap recover``: a recorder killed with SIGKILL loses at most what it had
not flushed, and recovery gets back everything it had."""

from __future__ import annotations

import asyncio
import io
import os
import signal
import struct
import zlib
from pathlib import Path

import pytest

from mcap.stream_reader import StreamReader
from mcap.records import Message

from whiztap.analyzer.recording.mcap import MAGIC
from whiztap.analyzer.recording.recover import RecoverResult, recover
from whiztap.analyzer.recording.scan import RecordingScan
from tests.cli_support import WHIZTAP, run_cli
from tests.record_support import WAIT, EchoServer, RecordProcess, read_all, streams, tcp_reads
from tests.test_hostile_files import MIB, corrupt_data, flip_crc, read_chunks, run_measured, write_recording


def _flushed_reads(part: str) -> bytes:
    """The client's bytes the .part holds so far (its complete chunks)."""
    with open(part, "rb") as f:
        return b"".join(r.data for r in tcp_reads(RecordingScan(f)) if r.dir == "c2s")


def _complete(result: RecoverResult) -> bool:
    """Everything in the input was copied: nothing skipped, cut or dropped."""
    return result.cut_at is None and not result.skipped and not result.orphans


@pytest.mark.slow
async def test_sigkill_mid_session_then_recover_gets_back_everything_flushed(tmp_path):
    out = tmp_path / "crash.mcap"
    part = str(out) + ".part"
    async with EchoServer() as server:
        rec = await RecordProcess.start(server.port, out, new_session=True)
        reader, writer = await asyncio.open_connection("127.0.0.1", rec.port)
        sent = b""
        for batch in range(3):
            frames = b"".join(b"rr1-%d--%d--0-ss1" % (i % 24, batch) for i in range(200))
            writer.write(frames)
            sent += frames
            await asyncio.wait_for(reader.readexactly(len(frames)), WAIT)
            for _ in range(int(WAIT * 20)):  # until the writer has flushed it (at most ~1 s)
                if _flushed_reads(part) == sent:
                    break
                await asyncio.sleep(0.05)
            assert _flushed_reads(part) == sent
        writer.write(b"rr1-0--0--0-ss1" * 50)  # likely not flushed: may be lost
        await reader.readexactly(15 * 50)
        os.killpg(rec.proc.pid, signal.SIGKILL)  # the recorder and its writer, mid-session
        await rec.proc.wait()
        writer.close()
    assert not out.exists()
    with open(part, "rb") as f:
        on_disk = 0
        try:
            for record in StreamReader(f, validate_crcs=True).records:
                on_disk += isinstance(record, Message)
        except Exception:  # the cut, wherever the kill fell
            pass
    code, stdout, stderr = run_cli("recover", part)
    assert (code, stderr) == (0, ""), stderr
    assert stdout == f"recovered {on_disk:,} messages into {out}\n" or \
        stdout.startswith(f"recovered {on_disk:,} messages into {out}; the file ended mid-write at byte ")
    by_topic = read_all(str(out))  # indexed, CRCs checked, schemas valid
    assert sum(len(m) for m in by_topic.values()) == on_disk
    assert streams(str(out))[(1, "c2s")].startswith(sent)
    assert os.path.exists(part)  # the original is left alone


async def test_recover_refuses_clearly(tmp_path):
    junk = tmp_path / "junk.mcap.part"
    junk.write_bytes(b"not an mcap file at all")
    code, _, err = run_cli("recover", str(junk))
    assert code == 2 and err.count("\n") == 1 and err.startswith("whiztap: ") and "not an MCAP file" in err
    code, _, err = run_cli("recover", str(tmp_path / "missing.part"))
    assert code == 2 and err == f"whiztap: {tmp_path / 'missing.part'}: no such file\n"
    (tmp_path / "junk.mcap").write_bytes(b"")
    code, _, err = run_cli("recover", str(junk))
    assert code == 2 and "exists; use --force" in err


async def test_recover_of_a_finished_file_copies_it_whole(tmp_path):
    out = tmp_path / "fine.mcap"
    async with EchoServer() as server:
        rec = await RecordProcess.start(server.port, out)
        reader, writer = await asyncio.open_connection("127.0.0.1", rec.port)
        writer.write(b"rr1-24--0--0-ss1")
        await reader.readexactly(16)
        writer.close()
        await rec.finish()
    result = recover(str(out), str(tmp_path / "copy.mcap"))
    assert _complete(result)
    original, copy = read_all(str(out)), read_all(result.output)
    assert copy == original and result.messages == sum(len(m) for m in original.values())


async def test_a_missing_input_is_said_before_an_existing_output(tmp_path):
    (tmp_path / "gone.mcap").write_bytes(b"a recording already there")
    code, _, err = run_cli("recover", str(tmp_path / "gone.mcap.part"))
    assert code == 2 and err == f"whiztap: {tmp_path / 'gone.mcap.part'}: no such file\n"


# -- damaged files: skip the damage, salvage the rest, say what was lost and where --------------------


def _messages(path: Path) -> list[tuple[int, int, bytes]]:
    """(channel id, log time, data) of every message of a finished file, sorted."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        return sorted((m.channel_id, m.log_time, m.data) for _, _, m in reader.iter_messages(log_time_order=False))


def _chunk_messages(data: bytes, at: int) -> list[tuple[int, int, bytes]]:
    """(channel id, log time, data) of the messages in the chunk at ``at``."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import Chunk
    from mcap.stream_reader import breakup_chunk

    length = struct.unpack_from("<Q", data, at + 1)[0]
    chunk = Chunk.read(ReadDataStream(io.BytesIO(data[at + 9:at + 9 + length])))
    return [(m.channel_id, m.log_time, m.data) for m in breakup_chunk(chunk) if isinstance(m, Message)]


def _without(messages: list, lost: list) -> list:
    left = list(messages)
    for m in lost:
        left.remove(m)
    return left


def _bad_record_length(buf: bytearray, at: int) -> bytearray:
    """The chunk at ``at`` rebuilt with its first record's length past its end
    (its CRC and compression intact: only walking its records finds it)."""
    import zstandard

    length = struct.unpack_from("<Q", buf, at + 1)[0]
    body = bytes(buf[at + 9:at + 9 + length])
    n = struct.unpack_from("<I", body, 28)[0]
    records = bytearray(zstandard.ZstdDecompressor().decompress(body[32 + n + 8:], max_output_size=1 << 24))
    struct.pack_into("<Q", records, 1, len(records))
    compressed = zstandard.ZstdCompressor().compress(bytes(records))
    new = body[:16] + struct.pack("<QI", len(records), zlib.crc32(records)) + body[28:32 + n] + \
        struct.pack("<Q", len(compressed)) + compressed
    return buf[:at] + struct.pack("<BQ", 0x06, len(new)) + new + buf[at + 9 + length:]


def _junk_length(buf: bytearray, at: int) -> bytearray:
    struct.pack_into("<Q", buf, at + 1, 1 << 40)  # the chunk's own length: now past the end of the file
    return buf


DAMAGE = {
    "bad CRC": lambda buf, at: flip_crc(buf, at + 9) or buf,
    "corrupt zstd": lambda buf, at: corrupt_data(buf, at + 9) or buf,
    "bad record length": _bad_record_length,
    "junk in the chunk's length": _junk_length,
}


@pytest.mark.parametrize("damage", sorted(DAMAGE))
def test_a_damaged_chunk_is_skipped_and_every_chunk_after_it_recovered(tmp_path, damage):
    original = write_recording(tmp_path / "r.mcap")
    data = original.read_bytes()
    at = read_chunks(data)[3]  # a chunk of TCP reads with others before and after it
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(bytes(DAMAGE[damage](bytearray(data), at)))
    out = tmp_path / "out.mcap"
    code, stdout, stderr = run_cli("recover", broken, "-o", out)
    assert (code, stderr) == (0, ""), stderr
    lost = _chunk_messages(data, at)
    expected = _without(_messages(original), lost)
    assert stdout.startswith(f"recovered {len(expected):,} messages into {out}; skipped 1 damaged region "
                             f"(at byte {at}: ") and stdout.count("\n") == 1, stdout
    assert lost and _messages(out) == sorted(expected)


def test_junk_between_chunks_costs_the_junk_only(tmp_path):
    original = write_recording(tmp_path / "r.mcap")
    data = original.read_bytes()
    at = read_chunks(data)[3]
    junk = bytes(range(7, 256)) * 400  # no chunk header adds up in it
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(data[:at] + junk + data[at:])
    result = recover(str(broken), str(tmp_path / "out.mcap"))
    assert [(s.offset, s.length) for s in result.skipped] == [(at, len(junk))] and result.cut_at is None
    assert _messages(result.output) == _messages(original)


def test_damage_and_a_cut_are_both_said(tmp_path):
    original = write_recording(tmp_path / "r.mcap")
    data = bytearray(original.read_bytes())
    chunks = read_chunks(bytes(data))
    flip_crc(data, chunks[2] + 9)
    cut = chunks[-1] + 100
    broken = tmp_path / "broken.mcap.part"
    broken.write_bytes(bytes(data[:cut]))
    code, stdout, stderr = run_cli("recover", broken)
    assert (code, stderr) == (0, "")
    assert f"; skipped 1 damaged region (at byte {chunks[2]}: " in stdout
    assert stdout.endswith(f"; the file ended mid-write at byte {chunks[-1]} (the 100 B after it could not be "
                           "read)\n"), stdout
    assert (tmp_path / "broken.mcap").exists()


def test_recovery_takes_the_limit_it_is_given_and_says_which_chunks_were_past_it(tmp_path, monkeypatch):
    original = write_recording(tmp_path / "r.mcap", chunk_size=2048)
    monkeypatch.setenv("WHIZTAP_MAX_CHUNK", "lots")  # not read when a limit is passed in
    result = recover(str(original), str(tmp_path / "out.mcap"), max_chunk=1024)
    assert result.skipped and all(s.too_big for s in result.skipped)
    assert "larger than WHIZTAP_MAX_CHUNK allows" in result.summary()
    whole = recover(str(original), str(tmp_path / "whole.mcap"), max_chunk=1 << 20)
    assert _complete(whole) and _messages(whole.output) == _messages(original)


def test_a_file_named_like_the_old_temporary_is_left_alone(tmp_path):
    original = write_recording(tmp_path / "r.mcap")
    out = tmp_path / "out.mcap"
    bystander = tmp_path / "out.mcap.recovering"
    bystander.write_bytes(b"somebody's file")
    before = set(tmp_path.iterdir())
    result = recover(str(original), str(out))
    assert bystander.read_bytes() == b"somebody's file"
    assert set(tmp_path.iterdir()) == before | {out}  # and no temporary file left behind
    assert _complete(result) and _messages(out) == _messages(original)
    assert oct(out.stat().st_mode & 0o777) == oct(original.stat().st_mode & 0o777)  # not mkstemp's 0600


def test_a_failed_recovery_leaves_no_temporary_file(tmp_path):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(MAGIC + bytes(range(256)) * 16)
    code, _, err = run_cli("recover", junk, "-o", tmp_path / "out.mcap")
    assert code == 2 and err == f"whiztap: {junk} holds nothing to recover: no schema, channel, message or " \
                                "metadata could be read\n"
    assert list(tmp_path.iterdir()) == [junk]


@pytest.mark.slow
def test_200_mb_of_junk_inside_a_recording_is_crossed_in_bounded_memory(tmp_path):
    original = write_recording(tmp_path / "r.mcap")
    data = original.read_bytes()
    at = read_chunks(data)[3]
    broken = tmp_path / "broken.mcap"
    junk = 200 * 1000 * 1000
    with open(broken, "wb") as f:
        f.write(data[:at])
        for _ in range(junk // MIB):
            f.write(os.urandom(MIB))
        f.write(os.urandom(junk % MIB))
        f.write(data[at:])
    code, stdout, stderr, peak, _ = run_measured([WHIZTAP, "recover", str(broken), "-o", str(tmp_path / "out.mcap")])
    assert (code, stderr) == (0, "") and f"; skipped 1 damaged region (at byte {at}: 200.0 MB)" in stdout, stdout
    assert peak < 100 * MIB, peak >> 20  # it is read a window at a time, never whole
    assert _messages(tmp_path / "out.mcap") == _messages(original)


def test_zeros_after_the_magic_end_at_once(tmp_path):
    zeros = tmp_path / "zeros.mcap.part"
    with open(zeros, "wb") as f:
        f.write(MAGIC)
        f.truncate(len(MAGIC) + 100 * MIB)  # a file system that zero-filled what was never written
    code, _, err, _, took = run_measured([WHIZTAP, "recover", str(zeros)])
    assert code == 2 and "holds nothing to recover" in err, (err, took)  # (38 s before; run_measured kills a hang)
