"""The middle's sans-IO core (analyzer/mitm/core.py) on a fake clock: every
fault's timing, holds and their timeout, injection, flow control, the end of a
connection, and the password rule in what it emits.  Events in, commands out;
nothing sleeps (tests/core_support.py moves the clock)."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from whiztap.analyzer.mitm.commands import Closing, Deliver, EndConnection, Full, WakeAt
from whiztap.analyzer.mitm.lane import HIGH_WATER, INJECT_ROOM, STALL_NS
from whiztap.analyzer.protocol.text import escape
from whiztap.analyzer.traffic import Action, Cause, Source
from whiztap.sniffer.mitm.controller import ControlError
from tests.core_support import C2S, MS, S, S2C, FakeClockMiddle, NotingShell
from tests.streams import chunked

REQ = b"rr1-12--0--0-ss1"
ANS = b"cr1-12--457--0-ss1"


def answers(n: int) -> bytes:
    return b"".join(b"cr1-12--%d--0-ss1" % (100 + i) for i in range(n))


# -- nothing chosen: every byte passes, in order, at once ---------------------------------------------


@settings(max_examples=60, deadline=None)
@given(st.data())
def test_bytes_no_fault_chose_pass_at_once_however_they_are_cut(data):
    stream = REQ + b"rr1-13--0--0-ss1\r\n" + b"xx" + b"sr1-24--1--0-ss1"
    mid = FakeClockMiddle("drop dir:s2c")  # a fault in force, choosing nothing the client sends
    for piece in chunked(stream, data.draw(st.lists(st.integers(1, 8), max_size=len(stream)))):
        mid.send(C2S, piece)
    mid.advance(STALL_NS)  # the unfinished "xx" would wait for its end; it passes after a stall
    assert mid.got(C2S) == stream
    assert b"".join(e.data for e in mid.delivered_events(C2S)) == stream
    assert mid.reads(C2S) == stream and not mid.interventions()


def test_a_timer_that_fires_early_asks_to_be_woken_again():
    mid = FakeClockMiddle("delay:20ms dir:s2c")
    mid.send(S2C, ANS)
    due = mid.shell.wake_at
    mid.shell.run(mid.core.wake(due - 1))  # an event loop's timer may fire a little early
    assert mid.got(S2C) == b"" and mid.shell.wake_at == due
    mid.advance(20 * MS)
    assert mid.got(S2C) == ANS


def test_a_frame_fed_one_byte_at_a_time_is_decided_once_whole():
    mid = FakeClockMiddle("delay:10ms dir:c2s")
    for i in range(len(REQ)):
        mid.send(C2S, REQ[i:i + 1])
    assert mid.got(C2S) == b"" and mid.shell.wake_at == mid.now + 10 * MS
    mid.advance(10 * MS)
    assert mid.writes(C2S) == [REQ]
    [delay] = mid.interventions(Action.DELAY)
    assert (delay.index, delay.offset, delay.delivered) == (0, 0, 0)


# -- delay, jitter, bandwidth, slice -----------------------------------------------------------------


def test_delay_holds_every_answer_back_and_keeps_their_order():
    mid = FakeClockMiddle("delay:300ms dir:s2c")
    mid.send(S2C, ANS)
    mid.advance(100 * MS)
    mid.send(S2C, answers(1))
    mid.advance(199 * MS)
    assert mid.got(S2C) == b""
    mid.advance(1 * MS)
    assert mid.got(S2C) == ANS  # 300 ms after it came
    mid.advance(99 * MS)
    assert mid.got(S2C) == ANS
    mid.advance(1 * MS)
    assert mid.got(S2C) == ANS + answers(1)
    delays = mid.interventions(Action.DELAY)
    assert [d.delivered for d in delays] == [0, len(ANS)] and [d.index for d in delays] == [0, 1]


def test_jitter_varies_each_delay_within_its_bounds_and_never_reorders():
    def run(seed: int) -> tuple[list[int], list[str]]:
        mid = FakeClockMiddle("delay:200ms dir:s2c jitter:50ms", seed=seed)
        for i in range(24):  # answers 10 ms apart: jitter alone would reorder them
            mid.send(S2C, b"cr1-%d--5--0-ss1" % (12 + i))
            mid.advance(10 * MS)
        mid.advance(S)
        assert mid.got(S2C) == b"".join(b"cr1-%d--5--0-ss1" % (12 + i) for i in range(24))
        return mid.write_times(S2C), [d.detail for d in mid.interventions(Action.DELAY)]

    times, details = run(3)
    assert (times, details) == run(3) and times == sorted(times)
    assert len(set(details)) > 1 and all(150 <= float(d.split()[1]) <= 250 for d in details)


def test_bandwidth_paces_many_small_answers_too():
    mid = FakeClockMiddle("bandwidth:2kB/s dir:s2c")
    start = mid.now
    for _ in range(60):
        mid.send(S2C, ANS)  # each answer shorter than a write, yet not sent back to back
    mid.advance(2 * S)
    assert mid.got(S2C) == ANS * 60
    assert mid.write_times(S2C)[-1] - start >= (60 * len(ANS) - 20) * S // 2000


def test_bandwidth_paces_a_direction_at_its_rate():
    mid = FakeClockMiddle("bandwidth:2kB/s dir:s2c")  # 20 bytes every 10 ms
    mid.send(S2C, answers(5))  # 85 bytes
    start = mid.now
    mid.advance(S)
    writes = mid.writes(S2C)
    assert b"".join(writes) == answers(5) and max(len(w) for w in writes) <= 20
    times = mid.write_times(S2C)
    assert times[-1] - start >= (85 - 20) * S // 2000  # 85 bytes at 2 kB/s: the last write 32.5 ms or more on


def test_slice_writes_pieces_a_pause_apart():
    mid = FakeClockMiddle("slice:4 dir:s2c pause:5ms")
    mid.send(S2C, ANS)
    assert mid.writes(S2C) == [ANS[:4]] and mid.shell.wake_at == mid.now + 5 * MS
    mid.advance(20 * MS)
    assert mid.writes(S2C) == [ANS[i:i + 4] for i in range(0, len(ANS), 4)]


# -- when: after, for, every, nth ------------------------------------------------------------------


def test_after_a_time_and_for_a_time_bound_when_a_fault_acts():
    mid = FakeClockMiddle("drop dir:s2c after:1s for:500ms")
    for _ in range(20):  # one answer each 100 ms for 2 s
        mid.send(S2C, ANS)
        mid.advance(100 * MS)
    drops = mid.interventions(Action.DROP)
    assert [d.index for d in drops] == [10, 11, 12, 13, 14]  # from 1 s, for half a second
    assert mid.got(S2C) == ANS * 15


def test_every_and_nth_count_the_frames_they_choose():
    mid = FakeClockMiddle("drop dir:s2c every:3", "dup dir:s2c nth:2")
    mid.send(S2C, ANS * 7)
    assert [d.index for d in mid.interventions(Action.DROP)] == [2, 5]
    [dup] = mid.interventions(Action.DUP)
    assert dup.index == 1 and mid.got(S2C) == ANS * 6


def test_after_a_count_lets_that_many_chosen_frames_pass_first():
    mid = FakeClockMiddle("drop dir:s2c kind:response after:3")
    mid.send(S2C, answers(6))
    assert mid.got(S2C) == answers(3) and [d.index for d in mid.interventions(Action.DROP)] == [3, 4, 5]


def test_prob_with_a_seed_hits_the_same_frames_every_run():
    def hits(seed: int) -> list[int]:
        mid = FakeClockMiddle("drop dir:c2s kind:command prob:0.5", seed=seed)
        mid.send(C2S, b"".join(b"rr1-%d--0--0-ss1" % ch for ch in range(12, 24)))
        return [d.index for d in mid.interventions(Action.DROP)]

    assert hits(5) == hits(5) and 0 < len(hits(5)) < 12 and hits(5) != hits(6)


def test_conn_aims_a_fault_at_one_connection():
    mid = FakeClockMiddle('replace:"cr1-12--999--0-ss1" dir:s2c ch:12 conn:2', "reset after:300ms conn:2")
    other = NotingShell()
    two, commands = mid.controller.open(2, other)
    other.run(commands)
    for direction in (C2S, S2C):
        other.run(two.ready(direction, mid.now))
    mid.send(S2C, ANS)
    other.run(two.received(S2C, ANS, mid.now))
    assert mid.got(S2C) == ANS and b"".join(c.data for c in other.commands if type(c) is Deliver) == \
        b"cr1-12--999--0-ss1"
    assert mid.shell.wake_at is None and other.wake_at == mid.now + 300 * MS
    other.run(two.wake(other.wake_at))
    assert [c.how for c in other.commands if type(c) is EndConnection] == [Action.RESET] and not mid.ended()


def test_reset_after_a_time_acts_on_its_timer_with_no_frame_needed():
    mid = FakeClockMiddle("reset after:2s")
    assert mid.shell.wake_at == mid.now + 2 * S
    mid.advance(2 * S - 1)
    assert not mid.ended()
    mid.advance(1)
    assert mid.ended() == [Action.RESET]
    [reset] = mid.interventions(Action.RESET)
    assert reset.cause == Cause(Source.FAULT, "fault-1", "reset after:2s") and reset.index == -1


def test_close_after_n_frames_follows_the_nth_frame():
    mid = FakeClockMiddle("close dir:c2s after:3")
    mid.send(C2S, REQ * 5)
    assert mid.got(C2S) == REQ * 3 and mid.ended() == [Action.CLOSE]


def test_a_reset_in_place_of_a_frame_is_one_intervention_told_once():
    mid = FakeClockMiddle("reset dir:s2c nth:2")
    mid.send(S2C, ANS * 3)
    [reset] = mid.interventions()
    assert (reset.action, reset.index, reset.offset, reset.before, reset.after) == (
        Action.RESET, 1, len(ANS), ANS, b"")
    assert mid.got(S2C) == ANS and mid.ended() == [Action.RESET]


def test_an_expired_frame_says_where_it_was_in_its_senders_stream():
    mid = FakeClockMiddle("delay:1s dir:s2c nth:2")
    mid.send(S2C, ANS * 2)
    mid.shell.run(mid.core.lost(C2S, mid.now))
    [expired] = mid.interventions(Action.EXPIRE)
    assert (expired.index, expired.offset) == (1, len(ANS))


def test_blackhole_swallows_and_keeps_the_connection():
    mid = FakeClockMiddle("blackhole dir:s2c after:1s")
    mid.send(S2C, ANS)
    mid.advance(S)
    mid.send(S2C, ANS * 3)
    assert mid.got(S2C) == ANS and len(mid.interventions(Action.BLACKHOLE)) == 3 and not mid.ended()


# -- holds -----------------------------------------------------------------------------------------


def test_a_held_frame_holds_back_what_follows_until_released_edited_or_dropped():
    mid = FakeClockMiddle(intercept="dir:c2s ch:13")
    mid.send(C2S, b"rr1-13--0--0-ss1" + REQ)
    assert mid.got(C2S) == b""
    [held] = mid.controller.held.frames.values()
    assert (held.index, held.offset, held.shown) == (0, 0, b"rr1-13--0--0-ss1")
    mid.controller.release(held.id, edit="rr1-14--0--0-ss1")
    assert mid.got(C2S) == b"rr1-14--0--0-ss1" + REQ
    hold, edit = mid.interventions()
    assert (hold.action, hold.held, edit.action, edit.held, edit.delivered) == (
        Action.HOLD, held.id, Action.EDIT, held.id, 0)
    mid.send(C2S, b"rr1-13--0--0-ss1")
    [again] = mid.controller.held.frames.values()
    mid.controller.drop(again.id)
    assert mid.got(C2S) == b"rr1-14--0--0-ss1" + REQ and mid.interventions()[-1].action is Action.DROP


def test_a_forgotten_hold_is_released_by_its_timeout():
    mid = FakeClockMiddle(intercept="dir:c2s", hold_timeout=0.5)
    mid.send(C2S, REQ)
    mid.advance(499 * MS)
    assert mid.got(C2S) == b""
    mid.advance(1 * MS)
    assert mid.got(C2S) == REQ
    release = mid.interventions(Action.RELEASE)[0]
    assert release.cause == Cause(Source.TIMEOUT, text="0.5 s") and not mid.controller.held.frames


# -- injection and flow control ------------------------------------------------------------------------


def test_an_injection_goes_after_what_is_decided_and_says_where_it_went():
    mid = FakeClockMiddle()
    mid.send(S2C, ANS)
    mid.controller.inject(1, "s2c", "cr1-13--5--0-ss1")
    assert mid.got(S2C) == ANS + b"cr1-13--5--0-ss1"
    [inject] = mid.interventions(Action.INJECT)
    assert (inject.delivered, inject.index, inject.cause.source) == (len(ANS), -1, Source.INJECTION)


def test_a_replace_that_grows_each_frame_stops_reading_its_sender_not_the_memory():
    mid = FakeClockMiddle("replace:'" + "x" * 60_000 + "' dir:s2c", ready=False)  # the client never reads
    mid.shell.run(mid.core.ready(C2S, mid.now))
    for _ in range(200):
        mid.send(S2C, answers(100))  # 1,800 bytes a read, each frame to become 60 kB
    lane = mid.core.lanes[S2C]
    assert lane.queued <= HIGH_WATER + 60_000 + 200 * 1_800
    assert not mid.core.may_read(S2C)  # the proxy stops reading the server


@pytest.mark.slow
def test_an_injection_past_the_room_is_refused_and_the_proxy_says_so():
    mid = FakeClockMiddle(ready=False)
    frame = "cr1-12--" + "9" * (INJECT_ROOM // 16 - 15) + "--0-ss1"  # 16 fill the room; too wide: forced
    with pytest.raises(ControlError) as refused:
        for _ in range(INJECT_ROOM // len(frame) + 2):
            mid.controller.inject(1, "s2c", frame, True)
    assert refused.value.status == 429
    with pytest.raises(Full):
        mid.core.inject(S2C, b"x", Cause(Source.INJECTION), mid.now)


# -- the end -----------------------------------------------------------------------------------------


def test_a_frame_due_after_its_receiver_is_gone_expires_and_nothing_is_written():
    mid = FakeClockMiddle("delay:300ms dir:s2c")
    mid.send(S2C, ANS)
    mid.shell.run(mid.core.lost(C2S, mid.now))  # the client went away
    mid.advance(S)
    assert mid.got(S2C) == b""
    [expired] = mid.interventions(Action.EXPIRE)
    assert (expired.before, expired.index) == (ANS, 0)
    [delay] = mid.interventions(Action.DELAY)
    assert delay.delivered == -1
    with pytest.raises(Closing, match="connection 1 is closing"):
        mid.core.inject(C2S, REQ, Cause(Source.INJECTION), mid.now)
    with pytest.raises(ControlError) as refused:
        mid.controller.inject(1, "c2s", "sensor 12")
    assert refused.value.status == 409
    mid.controller.closed(1)
    assert mid.shell.commands[-1] == WakeAt(None) or mid.shell.wake_at is None


def test_a_fin_passes_once_what_waits_before_it_is_delivered():
    mid = FakeClockMiddle("delay:100ms dir:s2c")
    mid.send(S2C, ANS)
    mid.shell.run(mid.core.sender_ended(S2C, mid.now))
    assert mid.eofs() == []
    mid.advance(100 * MS)
    assert mid.got(S2C) == ANS and mid.eofs() == [S2C]


def test_an_unfinished_item_passes_after_a_stall_and_a_password_at_once():
    mid = FakeClockMiddle()
    mid.send(C2S, b"rr1-1")
    assert mid.got(C2S) == b""
    mid.advance(STALL_NS)
    assert mid.got(C2S) == b"rr1-1"
    winsock = FakeClockMiddle()
    winsock.send(S2C, b"sendchkpass")
    winsock.send(C2S, b"hunt")  # the server may be waiting for these bytes to judge them
    assert winsock.got(C2S) == b"hunt"


# -- secrets -------------------------------------------------------------------------------------------


@pytest.mark.parametrize("redact", [True, False])
def test_an_eager_password_under_a_fault_is_masked_in_everything_the_core_emits(redact):
    mid = FakeClockMiddle("delay:1ms dir:c2s", intercept="dir:c2s", redact=redact)
    mid.send(C2S, b"Zq7secretPW\r\n")  # before the server's greeting
    mid.send(S2C, b"sendchkpass")
    held = list(mid.controller.held.frames.values())
    assert (b"Zq7secretPW" in b"".join(h.shown for h in held)) is not redact
    assert ("Zq7secretPW" in str(mid.controller.held_frames())) is not redact
    assert mid.controller.release_all() == len(held) > 0
    mid.advance(S)
    assert mid.got(C2S) == b"Zq7secretPW\r\n"  # what is delivered is what the client sent
    shown = b"".join(i.before + i.after for i in mid.interventions())
    assert mid.interventions() and (b"Zq7secretPW" in shown) is not redact
    assert all(i.secret for i in mid.interventions() if i.direction is C2S)


def test_a_password_held_and_sent_back_as_its_mask_goes_as_it_came():
    mid = FakeClockMiddle(intercept="dir:c2s")
    mid.send(C2S, b"Zq7secretPW\r\n")  # eager: before the server's greeting, so held (and shown masked)
    hidden = [h for h in mid.controller.held.frames.values() if h.hidden]
    assert hidden
    for held in hidden:
        mid.controller.release(held.id, edit=escape(held.shown), force=True)  # Enter in the editor, unchanged
    mid.controller.release_all()
    assert mid.got(C2S) == b"Zq7secretPW\r\n"
