"""The help screen (``?``): every key, the modes, and the filter's words."""

from __future__ import annotations

from rich.markdown import Markdown
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import VerticalScroll
from textual.screen import ModalScreen
from textual.widgets import Static
from whiztap.analyzer.analysis.item_filter import FILTER_HELP

HELP = f"""\
# whiztap tui

Frames of the Progwhiz Robotics Server API (Rev 1.8), decoded and checked as
they pass.  A mark before a frame means it breaks a rule: **●** error,
**▲** warning, **·** info.

## Keys

- `j` / `↓`, `k` / `↑`: next / previous frame
- `PgDn` / `PgUp`: a page down / up
- `g` / `Home`: first frame
- `G` / `End`: last frame, and follow new frames (live and follow mode)
- `n` / `N`: next / previous frame with a violation
- `p`: the paired frame: a response's request, a request's response
- `/`: the filter bar (`Enter` applies, an empty filter shows everything, `Esc` leaves it);
  words that do not parse are refused on the bar and the filter in force stays
- `c`: the connections pane (`Enter` on a row shows only that connection; `all` shows every one)
- `d` / `s`: detail / statistics in the right pane
- `z`: hide or show the right pane (a wide frame list)
- `r`: the replay screen: replay this recording against a server
- `Tab`: next pane
- `?`: this help (`Esc` closes it)
- `q` (`Ctrl+q` in a text field): quit; a live recording is finished first
- `b`: bisect: a rule id (`PW-PAIR-UNANSWERED`), a family (`PW-PAIR`) or a severity (`error`)
  goes to the first frame in view with such a violation; two connections (`1 2`) show where they
  first differ, side by side (`Esc` returns on the first's frame there)

## The proxy in the middle (live and `whiztap demo`)

The same control layer as `whiztap ctl` (docs/faults.md); what the proxy did
shows as a glyph before the time (⏸ held, + injected, ✎ edited, ✗ dropped,
⏱ delayed, ⚡ faulted) and in the detail pane, and the filter words `held`,
`injected`, `edited`, `dropped`, `delayed`, `faulted` select those frames.

- `i`: intercept: hold the frames these filter words choose (`Enter` sets it; empty holds nothing
  more; `Esc` leaves it).  Held frames wait after the list's rows, with the seconds left before
  `--hold-timeout` lets them go as they are; the list's title counts them
- on a held frame: `a` let it go as it is, `x` drop it, `e` edit it; `A` let every held frame go
- `e`, the editor: the frame as escaped text (or console words, `sensor 13`), its fields and the
  rules it breaks beside it as you type; `Enter` lets it go as typed (a frame that breaks a rule
  asks once: `Enter` again sends it anyway); `Esc` leaves it held
- `I`: inject a frame into the selected frame's connection (or the one chosen with `c`): escaped
  text or console words (`sensor 12`, `servo 3 1500`), judged as you type; `Ctrl+T` toward the
  server or the client; `↑` / `↓` what was injected before; `Enter` sends (asks once before
  breaking a rule)
- `f`: the faults pane: the faults in force and the frames each has hit.  In it `a` adds one (a
  SPEC such as `drop dir:s2c kind:response every:2`; `Right` or `Tab` completes a word, the error
  shows as you type, `Enter` applies it), `d` removes the selected fault, `space` switches it off
  and on, `Esc` leaves the line, then the pane

## Modes

- **recording** (`whiztap tui FILE.mcap`): the file loads in the background;
  the first frames show at once.
- **live** (`whiztap tui --listen ADDR --upstream ADDR`): the recording proxy runs
  inside the app; clients connect to the listen address.
- **follow** (`whiztap tui --follow FILE.mcap.part`): a file another `whiztap record`
  is writing; frames show within a second of being flushed.

In live and follow mode the list follows new frames.  Moving up stops
following; the list's border counts the frames that arrived since; `End` follows again.

## Filter

`{FILTER_HELP}`

For example `conn:2 kind:response ch:12`, or `violations dir:c2s`, or `Servo`.
The same filter as `whiztap cat`; it is applied in the background.
"""


class HelpScreen(ModalScreen):
    BINDINGS = [Binding("escape,question_mark,q", "dismiss", "Close")]
    DEFAULT_CSS = """
    HelpScreen { align: center middle; }
    HelpScreen > VerticalScroll {
        width: 90; max-width: 100%; height: 90%;
        border: thick $primary; background: $surface; padding: 0 1;
    }
    """

    def compose(self) -> ComposeResult:
        with VerticalScroll():
            yield Static(Markdown(HELP))  # rendered at once (Textual's Markdown widget builds later)
