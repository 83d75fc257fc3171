"""The fault SPEC grammar (analyzer/mitm/spec.py): the examples parse to the
fields they say, every error names its word, TOML files, and no text makes the
parser raise anything but FaultSpecError."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from whiztap.analyzer.analysis.item_filter import ItemFilter, parse_filter
from whiztap.analyzer.mitm.fault_file import load_faults
from whiztap.analyzer.mitm.faults import MAX_FAULTS
from whiztap.analyzer.mitm.spec import (
    ACTIONS,
    ACTIONS_WITH_ARGUMENT,
    OPTIONS,
    FaultSpec,
    FaultSpecError,
    parse_duration,
    parse_fault,
)
from whiztap.analyzer.protocol.framing import Item, ItemKind
from whiztap.analyzer.protocol.messages import ChannelResponse
from whiztap.analyzer.protocol.observations import Direction, Observation

MS = 1_000_000
S = 1_000_000_000
RESPONSE, COMMAND, SET_CONFIG = ItemKind.RESPONSE, ItemKind.COMMAND, ItemKind.SET_CONFIG

EXAMPLES = [
    ("delay:200ms dir:s2c", dict(action="delay", delay_ns=200 * MS, select=ItemFilter(direction="s2c"))),
    ("delay:200ms dir:s2c jitter:50ms",
     dict(action="delay", delay_ns=200 * MS, jitter_ns=50 * MS, select=ItemFilter(direction="s2c"))),
    ("drop dir:s2c kind:response ch:12 every:2",
     dict(action="drop", every=2,
          select=ItemFilter(direction="s2c", kinds=frozenset({RESPONSE}), channels=frozenset({12})))),
    ("dup dir:c2s kind:command nth:1",
     dict(action="dup", nth=1, select=ItemFilter(direction="c2s", kinds=frozenset({COMMAND})))),
    ("corrupt dir:c2s kind:set_config",
     dict(action="corrupt", select=ItemFilter(direction="c2s", kinds=frozenset({SET_CONFIG})))),
    ('replace:"cr1-12--999--0-ss1" dir:s2c kind:response ch:12 nth:1',
     dict(action="replace", replacement=b"cr1-12--999--0-ss1", nth=1,
          select=ItemFilter(direction="s2c", kinds=frozenset({RESPONSE}), channels=frozenset({12})))),
    ("slice:1 dir:s2c", dict(action="slice", slice_sizes=(1, 1), pause_ns=MS, select=ItemFilter(direction="s2c"))),
    ("slice:2-8", dict(action="slice", slice_sizes=(2, 8), select=ItemFilter())),
    ("slice:2-8 pause:5ms", dict(action="slice", slice_sizes=(2, 8), pause_ns=5 * MS)),
    ("bandwidth:2kB/s dir:s2c", dict(action="bandwidth", rate=2000, select=ItemFilter(direction="s2c"))),
    ("blackhole dir:s2c after:2s", dict(action="blackhole", after_ns=2 * S, after_frames=None)),
    ("reset after:3s", dict(action="reset", after_ns=3 * S)),
    ("close dir:c2s after:10", dict(action="close", after_frames=10, after_ns=None)),
    ("drop prob:0.25 for:1.5s conn:2,3", dict(action="drop", prob=0.25, for_ns=1500 * MS,
                                             select=ItemFilter(conns=frozenset({2, 3})))),
    ("drop violations text:hello", dict(select=ItemFilter(violations_only=True, text="hello"))),
    ('drop text:"a b" dir:c2s', dict(select=ItemFilter(direction="c2s", text="a b"))),
    ("delay:250 jitter:1m", dict(delay_ns=250 * MS, jitter_ns=60 * S)),
    ("replace:'rr1-0--0--2-ss1\\r\\n'", dict(replacement=b"rr1-0--0--2-ss1\r\n")),
    ('replace:"sr1-\\x01000-ss1"', dict(replacement=b"sr1-\x01000-ss1")),
]


@pytest.mark.parametrize("text, fields", EXAMPLES, ids=[t for t, _ in EXAMPLES])
def test_the_examples_parse_to_their_fields(text, fields):
    spec = parse_fault(text, name="x")
    assert spec.text == text and spec.name == "x"
    for field, value in fields.items():
        assert getattr(spec, field) == value, field


@pytest.mark.parametrize("text", [t for t, _ in EXAMPLES])
def test_the_canonical_form_parses_back_to_the_same_fault(text):
    spec = parse_fault(text)
    again = parse_fault(spec.describe())
    assert again == FaultSpec(**{**spec.__dict__, "text": spec.describe()})
    assert again.describe() == spec.describe()


def test_canonical_forms():
    assert parse_fault("DROP kind:response,command dir:s2c ch:13,12 every:2").describe() == \
        "drop dir:s2c kind:command,response ch:12,13 every:2"
    assert parse_fault("delay:1.5s").describe() == "delay:1500ms"
    assert parse_fault("bandwidth:1KiB/s").describe() == "bandwidth:1KiB/s"
    assert parse_fault("bandwidth:2000000B/s").describe() == "bandwidth:2MB/s"


def test_bandwidth_units():
    rates = {"5B/s": 5, "2kB/s": 2000, "2KB/s": 2000, "2KiB/s": 2048, "1.5MB/s": 1_500_000, "1MiB/s": 1 << 20}
    for text, rate in rates.items():
        assert parse_fault(f"bandwidth:{text}").rate == rate


def test_durations():
    assert parse_duration("200ms") == 200 * MS
    assert parse_duration("1.5s") == 1500 * MS
    assert parse_duration("2m") == 120 * S
    assert parse_duration("10us") == 10_000 and parse_duration("7ns") == 7
    assert parse_duration("30") == 30 * MS
    assert parse_duration("30", bare_unit_ns=1) == 30
    for bad in ("", "ms", "-5ms", "5 ms", "5h", "1e3ms", "٣ms"):
        with pytest.raises(ValueError):
            parse_duration(bad)


def test_selects_reads_the_filter_words():
    spec = parse_fault("drop dir:s2c kind:response ch:12")
    response = ChannelResponse(12, 5)
    item = Item(RESPONSE, b"cr1-12--5--0-ss1", 7, 9)
    seen = Observation(0, Direction.S2C, item, response, (response,), ())
    assert spec.selects(1, seen)
    assert not spec.selects(1, seen._replace(direction=Direction.C2S))
    other = ChannelResponse(13, 5)
    assert not spec.selects(1, seen._replace(message=other, candidates=(other,)))
    assert not parse_fault("drop conn:2").selects(1, seen) and parse_fault("drop conn:1").selects(1, seen)


def test_the_tables_name_every_action_and_option():
    assert set(ACTIONS) == {"delay", "drop", "dup", "corrupt", "replace", "slice", "bandwidth",
                            "blackhole", "reset", "close"}
    assert {"delay", "replace", "slice", "bandwidth"} == ACTIONS_WITH_ARGUMENT
    assert {"nth", "every", "prob", "after", "for", "jitter", "pause"} <= set(OPTIONS)


ERRORS = [
    ("delay:200ms dri:s2c", "dri:s2c"),
    ("drop since:1", "since:1"),
    ("drop dir:s2c until:5", "until:5"),
    ("explode dir:s2c", "explode"),
    ("delay dir:s2c", "delay"),
    ("delay: dir:s2c", "delay:"),
    ("drop:3", "drop:3"),
    ("slice", "slice"),
    ("slice:0", "slice:0"),
    ("slice:8-2", "slice:8-2"),
    ("slice:a", "slice:a"),
    ("bandwidth:2kb/s", "bandwidth:2kb/s"),
    ("bandwidth:2kB", "bandwidth:2kB"),
    ("bandwidth:0B/s", "bandwidth:0B/s"),
    ("delay:fast", "delay:fast"),
    ("delay:5h", "delay:5h"),
    ("drop nth:0", "nth:0"),
    ("drop every:0", "every:0"),
    ("drop nth:x", "nth:x"),
    ("drop prob:2", "prob:2"),
    ("drop prob:nan", "prob:nan"),
    ("drop nth:1 every:2", "every:2"),
    ("drop nth:1 nth:2", "nth:2"),
    ("drop after:1.5", "after:1.5"),
    ("drop after:soon", "after:soon"),
    ("drop for:x", "for:x"),
    ("drop dir:up", "dir:up"),
    ("drop kind:answer", "kind:answer"),
    ("drop ch:x", "ch:x"),
    ("drop nth", "nth"),
    ("drop dup", "dup"),
    ("drop delay:5ms", "delay:5ms"),
    ("replace:'\ud800'", "replace:"),
    ("drop hello", "hello"),
    ("drop text:", "text:"),
    ("drop text:a text:b", "text:b"),
    ("drop dir", "dir"),
]


@pytest.mark.parametrize("text, word", ERRORS, ids=[t for t, _ in ERRORS])
def test_every_error_names_its_word(text, word):
    with pytest.raises(FaultSpecError) as caught:
        parse_fault(text)
    message = str(caught.value)
    assert word in message and "\n" not in message
    assert repr(text) in message


def test_an_unknown_word_lists_the_words_there_are():
    with pytest.raises(FaultSpecError) as caught:
        parse_fault("delay:200ms dri:s2c")
    assert str(caught.value).startswith("unknown word 'dri:s2c' in fault 'delay:200ms dri:s2c' "
                                        "(filter words: dir: kind: ch: conn: text: violations, options: nth: every: ")
    assert str(caught.value).endswith("; did you mean dir:s2c?")


# A word without a colon was text to find: these typos made faults that never acted, silently.
BARE_WORDS = [
    ("delay:200 ms dir:s2c", "ms", "did you mean delay:200ms?"),
    ("drop dir:s2c every2", "every2", "did you mean every:2?"),
    ("drop ch:12 dir:s2c nth:1 respones", "respones", "did you mean kind:response?"),
    ("bandwidth:2 kB/s", "kB/s", "did you mean bandwidth:2kB/s?"),
    ("drop dirs2c", "dirs2c", "did you mean dir:s2c?"),
    ("drop s2c", "s2c", "did you mean dir:s2c?"),
    ("drop violation", "violation", "did you mean violations?"),
    ("drop hello", "hello", "words after the action are KEY:VALUE or violations"),
    ('drop "a b"', "a b", "text:'a b'"),
]


@pytest.mark.parametrize("text, word, hint", BARE_WORDS, ids=[t for t, _, _ in BARE_WORDS])
def test_a_bare_word_is_an_error_that_guesses_what_was_meant(text, word, hint):
    with pytest.raises(FaultSpecError) as caught:
        parse_fault(text)
    message = str(caught.value)
    assert message.startswith(f"bare word {word!r} in fault {text!r}: ") and "\n" not in message
    assert hint in message
    assert "text:" in message  # how to find text in frames, now that a bare word does not


def test_text_to_find_is_an_explicit_word_and_its_canonical_form_quotes_it():
    spec = parse_fault('drop text:"sensor 12" dir:c2s')
    assert spec.select.text == "sensor 12"
    assert spec.describe() == "drop dir:c2s text:'sensor 12'"
    assert parse_fault(spec.describe()).select == spec.select
    assert parse_fault("drop TEXT:Ok").select.text == "Ok"


EXPLAINED = [
    ("delay:200ms dir:s2c", "delay 200 ms, s2c, all frames"),
    ("drop dir:s2c kind:response ch:12 every:2",
     "drop, s2c, every 2nd frame of kind response on channel 12 of each connection"),
    ("dup dir:c2s kind:command nth:1", "dup, c2s, only the 1st frame of kind command of each connection"),
    ("delay:1.5s jitter:50ms", "delay 1500 ms ± 50 ms, both directions, all frames"),
    ("slice:2-8 pause:5ms dir:s2c", "slice in pieces of 2 to 8 bytes, 5 ms apart, s2c, all frames"),
    ("bandwidth:2kB/s dir:s2c", "bandwidth 2 kB/s, s2c, all frames"),
    ("replace:'cr1-12--999--0-ss1\\r\\n' ch:12,13", "replace with 'cr1-12--999--0-ss1\\r\\n', "
                                                      "both directions, all frames on channels 12, 13"),
    ("reset after:3s", "reset each connection 3 s after it opens (or the fault is added)"),
    ("close dir:c2s after:10", "close, c2s, all frames, right after the 10th such frame of each connection"),
    ("drop prob:0.25 for:2m conn:2 violations text:ok",
     "drop, both directions, all frames of connection 2 that break a rule containing 'ok', "
     "each with probability 0.25, for 2 min once it begins"),
    ("blackhole dir:s2c after:2s kind:image",
     "blackhole, s2c, all frames of kind image, from 2 s after the connection opens (or the fault is added)"),
]


@pytest.mark.parametrize("text, words", EXPLAINED, ids=[t for t, _ in EXPLAINED])
def test_a_fault_says_what_it_will_do_in_words(text, words):
    assert parse_fault(text).explain() == words


@pytest.mark.parametrize("text", ["", "   ", 'drop "dir:s2c'])
def test_empty_or_unsplittable_text_is_an_error(text):
    with pytest.raises(FaultSpecError):
        parse_fault(text)


def test_the_filter_bar_still_parses_as_before():
    f = parse_filter("conn:1 d:s2c k:response ch:3 since:1.5 until:9 ! hello world")
    assert f == ItemFilter(conns=frozenset({1}), direction="s2c", kinds=frozenset({RESPONSE}),
                           channels=frozenset({3}), since_s=1.5, until_s=9.0, violations_only=True,
                           text="hello world")


def test_the_filter_bar_and_the_intercept_filter_take_text_as_a_fault_writes_it_too():
    assert parse_filter('text:"hello world" dir:c2s') == parse_filter('dir:c2s "hello world"')
    assert parse_filter("TEXT:Servo").text == "Servo"


# -- files -----------------------------------------------------------------------------------


def test_a_file_of_faults(tmp_path):
    path = tmp_path / "faults.toml"
    path.write_text('[faults.slow-server]\nspec = "delay:200ms dir:s2c"\n'
                    '[faults.flaky-answers]\nspec = "drop dir:s2c kind:response every:2"\n')
    slow, flaky = load_faults(path)
    assert (slow.name, slow.action, slow.delay_ns) == ("slow-server", "delay", 200 * MS)
    assert (flaky.name, flaky.action, flaky.every) == ("flaky-answers", "drop", 2)
    assert load_faults(str(path)) == [slow, flaky]


@pytest.mark.parametrize("content, words", [
    ('[faults.x]\nspec = "delay:200ms dir:s2c"\nspec = "drop"\n', ["not TOML", "line 3"]),
    ("[faults.quiet]\nnth = 2\n", ["'quiet'", "no spec"]),
    ('[faults.bad]\nspec = "delay:200ms dri:s2c"\n', ["'bad'", "dri:s2c"]),
    ('[faults.bad]\nspec = 5\n', ["'bad'", "not a string"]),
    ('[faults.typo]\nspec = "drop"\nnht = 2\n', ["'typo'", "nht"]),
    ('[fault.x]\nspec = "drop"\n', ["fault"]),
    ("", ["no faults"]),
    ('[faults]\nx = "drop"\n', ["'x'", "not a table"]),
])
def test_a_bad_file_is_one_line_naming_it(tmp_path, content, words):
    path = tmp_path / "faults.toml"
    path.write_text(content)
    with pytest.raises(FaultSpecError) as caught:
        load_faults(path)
    message = str(caught.value)
    assert message.startswith(str(path)) and "\n" not in message
    for word in words:
        assert word in message


@pytest.mark.parametrize("content", [
    "[faults.x]\nspec = " + "[" * 5000 + "]" * 5000 + "\n",
    "[faults.x]\nspec = " + "{a = " * 5000 + "1" + "}" * 5000 + "\n",
])
def test_a_file_nested_thousands_deep_is_one_line(tmp_path, content):
    path = tmp_path / "deep.toml"
    path.write_text(content)
    with pytest.raises(FaultSpecError) as caught:
        load_faults(path)
    assert str(caught.value) == f"{path}: not a fault file: its values are nested too deeply to read"


def test_a_file_of_more_faults_than_may_be_in_force_is_one_line(tmp_path):
    path = tmp_path / "many.toml"
    path.write_text("".join(f'[faults.f{i}]\nspec = "drop ch:{i}"\n' for i in range(MAX_FAULTS + 1)))
    with pytest.raises(FaultSpecError, match=f"^{path}: 257 faults; at most 256 may be in force at once$"):
        load_faults(path)
    path.write_text("".join(f'[faults.f{i}]\nspec = "drop ch:{i}"\n' for i in range(MAX_FAULTS)))
    assert len(load_faults(path)) == MAX_FAULTS


def test_a_missing_or_unreadable_file_names_it(tmp_path):
    for path, why in ((tmp_path / "nowhere.toml", "no such file"), (tmp_path, "cannot read")):
        with pytest.raises(FaultSpecError, match=why) as caught:
            load_faults(path)
        assert str(caught.value).startswith(str(path))
    binary = tmp_path / "binary.toml"
    binary.write_bytes(b"\xff\xfe[faults]")
    with pytest.raises(FaultSpecError, match="not TOML"):
        load_faults(binary)


# -- any text ----------------------------------------------------------------------------------

_WORDS = st.sampled_from([
    *ACTIONS, *(f"{a}:" for a in ACTIONS), *(f"{o}:" for o in OPTIONS), "dir:", "kind:", "ch:", "conn:",
    "since:", "violations", "!", "200ms", "2kB/s", "1-3", "s2c", "response", "0", "1", "2", "0.5", "'", '"',
    "\\x0", "\\r", ":", ",", " ", "nan", "\ud800", "é", "-", "text:", "every2", "ms", "kB/s", "respones",
])


@pytest.mark.slow
@settings(max_examples=500, deadline=None)
@given(st.one_of(st.text(), st.lists(_WORDS, max_size=12).map("".join)))
def test_any_text_parses_or_raises_a_fault_spec_error(text):
    try:
        spec = parse_fault(text)
    except FaultSpecError as e:
        assert "\n" not in str(e)
    else:
        assert isinstance(spec, FaultSpec) and spec.action in ACTIONS
        assert parse_fault(spec.describe()).describe() == spec.describe()
        assert spec.explain()
