"""No races at the close (issue 25, item 6).

A frame the middle still holds when its receiver goes (delayed, held, paced,
injected behind one of them) is never written: it is recorded as an
``expire`` intervention, in the file too.  A control command racing a FIN
or a reset (inject, release, edit, drop) is answered 409 ``connection N is
closing`` while the connection ends, 404 once it is gone, and never 500:
nothing is written after the FIN it follows.  Driven on the fake clock
through every order of events (tests/middle_drive.py), then once through a
real ``whiztap record --control`` whose terminal must show no traceback.
"""

from __future__ import annotations

import asyncio
import json
import re
import socket
import struct
import threading

import pytest

from whiztap.analyzer.recording.format import metadata_record
from whiztap.sniffer.mitm.controller import middle_metadata
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.writer import RecordingFile

from tests.middle_drive import C2S, MS, S2C, T0, Drive
from tests.record_support import CONTROL_TOKEN, LOCAL, WAIT, RecordProcess, post_status, read_all

SENSOR, ANSWER = b"rr1-12--0--0-ss1", b"cr1-12--5--0-ss1"
CLOSING = re.compile(r"^connection \d+ is closing")

# What keeps a frame of each direction back: (its setup, the direction it holds).
HOLDERS = {
    "delay s2c": (["delay:2s dir:s2c"], None, S2C),
    "delay c2s": (["delay:2s dir:c2s"], None, C2S),
    "bandwidth s2c": (["bandwidth:1B/s dir:s2c"], None, S2C),
    "slice s2c": (["slice:1 pause:1s dir:s2c"], None, S2C),
    "held s2c": ([], "dir:s2c", S2C),
    "held c2s": ([], "dir:c2s", C2S),
}
# How the receiver of the held direction goes: its socket lost (reset or closed under it), or both at once.
GOINGS = ("receiver reset", "both reset", "sender FIN then receiver reset")


def _setup(drive: Drive, faults: list[str], intercept: str | None) -> None:
    for spec in faults:
        assert drive.api("POST", "/faults", {"spec": spec})[0] == 201
    if intercept:
        drive.api("PUT", "/intercept", {"filter": intercept})
    drive.open(1)


def _frame_for(direction) -> bytes:
    return SENSOR if direction is C2S else ANSWER


def _receiver_goes(drive: Drive, direction, going: str) -> None:
    receiver_sends = S2C if direction is C2S else C2S  # the socket of the receiver is the one that sends the other way
    if going == "sender FIN then receiver reset":
        drive.fin(1, direction)
        drive.lose(1, receiver_sends)
    elif going == "receiver reset":
        drive.lose(1, receiver_sends)
    else:
        drive.close(1)
    drive.advance(MS)
    drive.lose(1, direction)
    drive.close(1)


def record(path, drive: Drive):
    metadata = metadata_record(source="proxy", secrets="kept", **middle_metadata([], 1))
    recorder = Recorder(RecordingFile(str(path), metadata), keep_secrets=True)
    recorder.start(T0)
    for event in drive.events:
        recorder.receive(event)
    recorder.stop(drive.t + MS)
    return read_all(str(path))


@pytest.mark.parametrize("going", GOINGS)
@pytest.mark.parametrize("holder", sorted(HOLDERS))
def test_a_frame_due_after_its_receiver_went_is_dropped_and_recorded_as_expired(tmp_path, holder, going):
    faults, intercept, direction = HOLDERS[holder]
    drive = Drive()
    _setup(drive, faults, intercept)
    frame = _frame_for(direction)
    drive.send(1, direction, frame * 2)  # the second one waits behind the first
    drive.advance(10 * MS)
    drive.api("POST", "/inject", {"conn": 1, "dir": direction.value, "frame": frame.decode()})  # behind them too
    got_before = drive.delivered(1, direction)
    assert len(got_before) < 3 * len(frame)  # something waits
    _receiver_goes(drive, direction, going)
    drive.settle()
    assert drive.delivered(1, direction) == got_before  # nothing written once its receiver went
    assert not drive.reports, drive.reports
    expired = [e for e in drive.events if getattr(e, "action", None) == "expire"]
    assert expired and all(e.direction is direction for e in expired)
    topics = record(tmp_path / "r.mcap", drive)
    written = [i for i in topics["/interventions"] if i["action"] == "expire"]
    assert len(written) == len(expired)  # in the file, though told after the connection closed
    assert all(i["cause"] == "connection ending" for i in written), written


# -- control commands racing the end ------------------------------------------------------------------

MOMENTS = ("client FIN passed on", "server FIN passed on", "client reset", "server reset", "closed")


def _to(drive: Drive, moment: str) -> None:
    if moment == "client FIN passed on":
        drive.fin(1, C2S)
    elif moment == "server FIN passed on":
        drive.fin(1, S2C)
    elif moment == "client reset":
        drive.lose(1, C2S)
    elif moment == "server reset":
        drive.lose(1, S2C)
    else:
        drive.lose(1, C2S)
        drive.lose(1, S2C)
    drive.advance(MS)


def _requests(held: list[dict]) -> list[tuple[str, str, dict | None]]:
    """Every command a person may send now: inject both ways, and release, edit, drop each held frame."""
    asked: list[tuple[str, str, dict | None]] = [
        ("POST", "/inject", {"conn": 1, "dir": "c2s", "frame": "sensor 12"}),
        ("POST", "/inject", {"conn": 1, "dir": "s2c", "frame": ANSWER.decode()}),
        ("POST", "/held/release-all", None)]
    for h in held:
        edit = "sensor 13" if h["dir"] == "c2s" else ANSWER.decode()
        asked += [("POST", f"/held/{h['id']}/release", {"edit": edit}), ("POST", f"/held/{h['id']}/release", {}),
                  ("POST", f"/held/{h['id']}/drop", None)]
    return asked


@pytest.mark.parametrize("moment", MOMENTS)
def test_a_command_racing_the_end_is_answered_409_or_done_never_500(moment):
    """Whatever a person asks as a FIN or reset goes by: done (200) while the
    way is open, 409 ``connection 1 is closing`` once it is not, 404 once the
    connection is gone; never a write after the FIN it follows (the drive's
    shell refuses one as a transport does), never a 500."""
    for order in range(3):  # the request before the event, between the FIN and its passing, after
        drive = Drive()
        _setup(drive, [], "dir:c2s")
        drive.send(1, C2S, SENSOR * 3)
        drive.send(1, S2C, ANSWER)
        _, answer = drive.api("GET", "/held")
        held = answer["held"]
        if order:
            _to(drive, moment)
        if order == 2:
            drive.settle()
        for method, path, body in _requests(held):
            status, answer = drive.api(method, path, body)  # never 500: Drive.api asserts it
            assert status in (200, 404, 409), (method, path, status, answer)
            if status == 409:
                assert CLOSING.match(answer["error"]), answer
        if not order:
            _to(drive, moment)
        drive.settle()  # nothing raises later either (a write after its FIN raises in the drive's shell)


def test_once_a_side_is_gone_every_command_is_refused_in_one_line():
    drive = Drive()
    _setup(drive, [], "dir:c2s")
    drive.send(1, C2S, SENSOR)
    _, answer = drive.api("GET", "/held")
    [held] = answer["held"]
    drive.lose(1, S2C)  # the server went: the connection is ending
    for method, path, body in _requests([held]):
        status, answer = drive.api(method, path, body)
        if path.startswith("/held/") and status == 404:  # the held frame expired as its receiver went
            assert "no held frame" in answer["error"], answer
            continue
        if path == "/held/release-all":
            assert (status, answer) == (200, {"released": 0}), answer
            continue
        assert (status, CLOSING.match(answer["error"]) is not None) == (409, True), (path, status, answer)


def test_an_injection_toward_a_side_already_sent_its_fin_is_409():
    """The client's FIN was passed on to the server: nothing more can be written to it."""
    drive = Drive()
    _setup(drive, [], None)
    drive.send(1, C2S, SENSOR)
    drive.fin(1, C2S)
    assert C2S in drive.shells[1].eof
    status, answer = drive.api("POST", "/inject", {"conn": 1, "dir": "c2s", "frame": "sensor 12"})
    assert status == 409 and CLOSING.match(answer["error"]), answer
    status, _ = drive.api("POST", "/inject", {"conn": 1, "dir": "s2c", "frame": ANSWER.decode()})
    assert status == 200  # the other way is still open
    assert drive.delivered(1, S2C).endswith(ANSWER)


# -- through whiztap record ------------------------------------------------------------------------------


class QuickServer:
    """Answers each client's first bytes at once, then closes (a FIN), from a thread."""

    def __init__(self) -> None:
        self.sock = socket.create_server((LOCAL, 0))
        self.port = self.sock.getsockname()[1]
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        self.sock.settimeout(0.1)
        while not self.stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except (TimeoutError, OSError):
                continue
            with conn:
                conn.settimeout(WAIT)
                try:
                    if conn.recv(64):
                        conn.sendall(ANSWER)
                except OSError:
                    pass

    def close(self) -> None:
        self.stop.set()
        self.thread.join(WAIT)
        self.sock.close()


def _hammer(control: str, stop: threading.Event, statuses: list[int]) -> None:
    """Injections on connection 1 both ways, and releases of held #1..#9, until told to stop."""
    bodies = [("/inject", {"conn": 1, "dir": "c2s", "frame": "sensor 12"}),
              ("/inject", {"conn": 1, "dir": "s2c", "frame": ANSWER.decode()})]
    bodies += [(f"/held/{n}/release", {"edit": "sensor 13"}) for n in range(1, 10)]
    while not stop.is_set():
        for path, body in bodies:
            statuses.append(post_status(f"http://{control}{path}", json.dumps(body).encode()))


@pytest.mark.slow
async def test_whiztap_record_shows_no_traceback_when_frames_and_commands_race_the_close(tmp_path):
    """Connections whose server answers and closes at once while their answer
    is delayed past the close, and while injections and releases hammer the
    API: every answer 200, 404, 409 or 429, the delayed answers expire in the
    file, and nothing on the proxy's terminal but its own lines."""
    server = QuickServer()
    path = tmp_path / "race.mcap"
    try:
        rec = await RecordProcess.start(server.port, path, "--control", "127.0.0.1:0", "--control-token",
                                        CONTROL_TOKEN, "--keep-secrets",
                                        "--fault", "delay:300ms dir:s2c", "--fault", "delay:5ms dir:c2s nth:2")
        m = re.search(r"control: http://(\S+) ", rec.first)
        assert m, rec.first
        stop, statuses = threading.Event(), []
        hammer = threading.Thread(target=_hammer, args=(m.group(1), stop, statuses), daemon=True)
        hammer.start()
        for _ in range(6):
            _reader, writer = await asyncio.open_connection(LOCAL, rec.port)
            writer.write(SENSOR)
            await writer.drain()
            await asyncio.sleep(0.05)  # the server answered and closed; its answer is due in 300 ms
            writer.get_extra_info("socket").setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            writer.transport.abort()  # the client resets meanwhile (a TCP reset, not a FIN)
            await asyncio.sleep(0.4)  # the delayed answer falls due after the close
        stop.set()
        await asyncio.to_thread(hammer.join, WAIT)
        code, out, err = await rec.finish()
    finally:
        server.close()
    said = [line for line in err.splitlines() if not line.startswith("fault-")]  # but each fault in words, at start
    assert code == 0 and said == [], err
    assert "Traceback" not in out
    assert statuses and set(statuses) <= {200, 404, 409, 429}, sorted(set(statuses))
    interventions = read_all(str(path))["/interventions"]
    assert any(i["action"] == "expire" and i["dir"] == "s2c" for i in interventions), \
        {i["action"] for i in interventions}
