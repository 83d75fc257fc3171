"""``whiztap recover``: a recorder killed with SIGKILL loses at most what it had
not flushed, and recovery gets back everything it had."""

from __future__ import annotations

import asyncio
import os
import signal

from mcap.stream_reader import StreamReader
from mcap.records import Message

from analyzer.recording import RecordingScan
from sniffer.recover import recover
from tests.record_support import WAIT, WHIZTAP, EchoServer, RecordProcess, read_all, streams


def _flushed_reads(part: str) -> bytes:
    """The client's bytes the .part holds so far (its complete chunks)."""
    with open(part, "rb") as f:
        return b"".join(r.data for r in RecordingScan(f).reads() if r.dir == "c2s")


async def _run(*args: str) -> tuple[int, str, str]:
    proc = await asyncio.create_subprocess_exec(WHIZTAP, *args, stdout=asyncio.subprocess.PIPE,
                                                stderr=asyncio.subprocess.PIPE)
    out, err = await asyncio.wait_for(proc.communicate(), WAIT)
    return proc.returncode, out.decode(), err.decode()


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
        except Exception:  # noqa: BLE001 - the cut, wherever the kill fell
            pass
    code, stdout, stderr = await _run("recover", part)
    assert (code, stderr) == (0, ""), stderr
    assert stdout == f"recovered {on_disk} messages into {out}\n" or \
        stdout == f"recovered {on_disk} messages into {out} (the rest of the file was cut off mid-write)\n"
    by_topic = read_all(str(out))  # indexed, CRCs checked, schemas valid
    assert sum(len(m) for m in by_topic.values()) == on_disk
    assert streams(str(out))[(1, "c2s")].startswith(sent)
    assert os.path.exists(part)  # the original is left alone


async def test_recover_refuses_clearly(tmp_path):
    junk = tmp_path / "junk.mcap.part"
    junk.write_bytes(b"not an mcap file at all")
    code, _, err = await _run("recover", str(junk))
    assert code == 2 and err.count("\n") == 1 and err.startswith("whiztap: ") and "not an MCAP file" in err
    code, _, err = await _run("recover", str(tmp_path / "missing.part"))
    assert code == 2 and err == f"whiztap: {tmp_path / 'missing.part'}: no such file\n"
    (tmp_path / "junk.mcap").write_bytes(b"")
    code, _, err = await _run("recover", str(junk))
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
    assert result.complete
    original, copy = read_all(str(out)), read_all(result.output)
    assert copy == original and result.messages == sum(len(m) for m in original.values())


async def test_a_missing_input_is_said_before_an_existing_output(tmp_path):
    (tmp_path / "gone.mcap").write_bytes(b"a recording already there")
    code, _, err = await _run("recover", str(tmp_path / "gone.mcap.part"))
    assert code == 2 and err == f"whiztap: {tmp_path / 'gone.mcap.part'}: no such file\n"
