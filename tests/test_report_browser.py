"""The HTML reports driven in headless Chromium (tests/browser_support.py):
they load offline with no console error and no request, their tables sort
and filter, a violation's link shows its frame, values from a recording are
shown as text, a 10,000-violation report opens and answers, and the page's
outline is compared with a snapshot (``--snapshot-update`` after a deliberate
change; look at the diff before committing it)."""

from __future__ import annotations

import asyncio
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from whiztap.analyzer.analysis.facts import Analysis, ViolationRecord
from whiztap.analyzer.analysis.report.content import build
from whiztap.analyzer.analysis.report.html import render_html

from tests.browser_support import open_report
from tests.cli_support import run_cli
from tests.test_output_safety import HOSTILE, record_hostile, shown
from tests.tui_support import ROOT, SAMPLES

VIOLATIONS = SAMPLES / "violations.mcap"


@pytest.fixture(scope="module")
def samples_report(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("report") / "report.html"
    done = run_cli("analyze", *sorted(SAMPLES.glob("*.mcap")), "--format", "html", "-o", out)
    assert done.returncode == 1, done.stderr
    return out


def rows_shown(page, table: str = "violations") -> list[list[str]]:
    """The text of each row the table shows now, cell by cell."""
    return page.eval_on_selector_all(f"#t-{table} tbody tr",
                                     "rows => rows.map(r => [...r.cells].map(c => c.innerText))")


def column_of(page, table: str, key: str) -> int:
    return page.eval_on_selector_all(f"#t-{table} thead th", f"hs => hs.findIndex(h => h.dataset.key === '{key}')")


def test_the_report_loads_offline_with_no_error(browser, samples_report):
    opened = open_report(browser, samples_report)
    assert opened.console_errors == [] and opened.page_errors == [] and opened.requests == []
    page = opened.page
    assert page.locator(".verdict").inner_text().startswith("FAIL: violations at or above error")
    headings = page.eval_on_selector_all("section > h2", "hs => hs.map(h => h.innerText)")
    assert headings[:2] == ["Violations", "Plots"]  # the verdict and the violations first
    assert page.locator("figure.plot canvas").count() >= 5  # items, violations, latency, sensor, servo


def test_rule_ids_are_never_broken(browser, samples_report):
    page = open_report(browser, samples_report, width=1000).page
    heights = page.eval_on_selector_all("#t-violations td.k-rule code",
                                        "cs => cs.map(c => c.getClientRects().length)")
    assert heights and set(heights) == {1}  # one line box each: never wrapped mid-word


def test_sorting_and_filtering_change_the_rows_shown(browser, samples_report):
    page = open_report(browser, samples_report).page
    conn = column_of(page, "violations", "conn")
    before = rows_shown(page)
    page.click("#t-violations th[data-key=conn]")
    ascending = [int(r[conn]) for r in rows_shown(page)]
    assert ascending == sorted(ascending)
    page.click("#t-violations th[data-key=conn]")
    descending = [int(r[conn]) for r in rows_shown(page)]
    assert descending == sorted(ascending, reverse=True) and len(descending) == len(before)

    page.select_option("#t-violations select[data-filter=rule]", "PW-SYNTAX-SPACE")
    shown_now = rows_shown(page)
    assert shown_now and {r[0] for r in shown_now} == {"PW-SYNTAX-SPACE"} and len(shown_now) < len(before)
    assert page.locator("#t-violations .count").inner_text() == f"{len(shown_now)} of {len(before)} rows"
    page.select_option("#t-violations select[data-filter=rule]", "")
    page.fill("#t-violations input[data-filter=text]", "checksum")
    assert 0 < len(rows_shown(page)) < len(before)
    assert all("checksum" in " ".join(r).lower() for r in rows_shown(page))


def test_a_violations_link_shows_its_frame_among_those_around_it(browser, samples_report):
    page = open_report(browser, samples_report).page
    frame = column_of(page, "violations", "frame")
    row = page.locator("#t-violations tbody tr").nth(5)
    wanted = row.locator("td").nth(frame).inner_text()
    row.locator("a.frames-link").click()
    dialog = page.locator("dialog#frame-view")
    assert dialog.is_visible()
    hit = dialog.locator("tr.hit")
    assert hit.count() == 1 and wanted[:60] in hit.inner_text()
    assert dialog.locator("tbody tr").count() > 1  # with the items around it
    assert "#frame/" in page.url
    dialog.locator("button.close").click()
    assert not dialog.is_visible()


def test_values_from_a_recording_are_shown_as_text_never_run(browser, tmp_path):
    recording = record_hostile(tmp_path / "evil-<b>.mcap")
    out = tmp_path / "report.html"
    run_cli("analyze", recording, "--format", "html", "-o", out)
    opened = open_report(browser, out)
    dialogs: list[str] = []
    opened.page.on("dialog", lambda d: (dialogs.append(d.message), d.dismiss()))
    assert opened.page_errors == [] and opened.requests == [] and dialogs == []
    text = opened.page.locator("#t-connections").inner_text()
    assert shown(HOSTILE) in text  # '<script>alert(1)</script>' and all, as text
    assert opened.page.locator("#report script").count() == 0 and opened.page.locator("#report b").count() == 0


def many_violations(n: int) -> str:
    """A report page with ``n`` listed violations, made without a recording."""
    rules = ("PW-SYNTAX-SPACE", "PW-RANGE-SENSOR", "PW-FRAME-GARBAGE", "PW-PAIR-UNANSWERED")
    analysis = Analysis(["many.mcap"], "dev-sum", max_violations=n, first_ns=0, last_ns=n * 1_000_000)
    for i in range(n):
        rule = rules[i % len(rules)]
        analysis.violations.append(ViolationRecord(rule, "many.mcap", 1 + i % 50, "c2s", i * 1_000_000,
                                                    b"rr1-0-- 5--0-ss1", f"violation {i}", index=i))
        analysis.violation_counts[rule] += 1
    return render_html(build(analysis), analysis)


@pytest.mark.slow
def test_ten_thousand_violations_open_and_answer(browser, tmp_path):
    out = tmp_path / "many.html"
    out.write_text(many_violations(10_000))
    opened = open_report(browser, out)
    page = opened.page
    assert opened.console_errors == [] and opened.page_errors == []
    assert page.locator("#t-violations .count").inner_text() == "10,000 rows (the first 1,000 shown)"
    assert page.locator("#t-violations tbody tr").count() == 1_000  # the rest drawn on demand
    page.click("#t-violations button.more")
    assert page.locator("#t-violations tbody tr").count() == 2_000
    page.select_option("#t-violations select[data-filter=rule]", "PW-RANGE-SENSOR")
    assert page.locator("#t-violations .count").inner_text() == "2,500 of 10,000 rows (the first 2,000 shown)"
    page.click("#t-violations th[data-key=t]")
    page.click("#t-violations th[data-key=t]")
    t = column_of(page, "violations", "t")
    assert float(rows_shown(page)[0][t]) == max(i / 1000 for i in range(1, 10_000, 4))


def outline(page) -> list[str]:
    """What the page shows, as lines: headings, paragraphs, each table's
    columns, count and first rows (plots as their titles; no canvas pixels)."""
    return page.evaluate("""() => {
      const lines = [];
      for (const node of document.querySelectorAll('#report h1, #report h2, #report h3, #report p, #report nav,'
                                                   + ' #report .table, #report figure.plot')) {
        if (node.matches('.table')) {
          lines.push('table ' + node.id + ': ' + [...node.querySelectorAll('th')].map(h => h.innerText).join(' | '));
          lines.push('  ' + node.querySelector('.count').innerText);
          for (const r of [...node.querySelectorAll('tbody tr')].slice(0, 3))
            lines.push('  ' + [...r.cells].map(c => c.innerText).join(' | '));
        } else if (node.matches('figure.plot')) {
          lines.push('plot ' + node.querySelector('.u-title').innerText + ': '
                     + [...node.querySelectorAll('.u-legend .u-label')].map(l => l.innerText).join(', '));
        } else lines.push(node.tagName.toLowerCase() + ' ' + node.innerText);
      }
      return lines;
    }""")


def test_the_page_matches_its_snapshot(browser, snapshot, tmp_path):
    out = tmp_path / "violations.html"  # the recording named from the top: the same page wherever the clone is
    assert run_cli("analyze", "samples/violations.mcap", "--format", "html", "-o", out, cwd=ROOT).returncode == 1
    page = open_report(browser, out).page
    assert outline(page) == snapshot
    page.locator("#t-violations a.frames-link").first.click()
    assert page.locator("dialog#frame-view").inner_text().splitlines() == snapshot


def test_the_probe_page_opens_a_cases_frames(browser, tmp_path):
    from whiztap.analyzer.probe.report import render
    from whiztap.sniffer.sim.simulator import Simulator

    from tests.test_probe_server import _probe

    async def run():
        async with Simulator(bugs=("out-of-range",)) as sim:
            return await _probe(sim, ("answer.sensor-request", "handshake.vpn"), record_dir=str(tmp_path / "rec"))

    out = tmp_path / "probe.html"
    with ThreadPoolExecutor(1) as thread:  # Playwright's sync API holds this thread's event loop
        out.write_text(render(thread.submit(asyncio.run, run()).result(), "html"))
    opened = open_report(browser, out)
    page = opened.page
    assert opened.console_errors == [] and opened.page_errors == [] and opened.requests == []
    assert page.locator("#t-failures tbody tr").count() == 1
    page.select_option("#t-cases select[data-filter=verdict]", "skip")
    assert [r[1] for r in rows_shown(page, "cases")] == ["skip"]
    page.select_option("#t-cases select[data-filter=verdict]", "")
    page.locator("#t-failures a.frames-link").click()
    dialog = page.locator("dialog#frame-view")
    assert dialog.is_visible() and "Sensor Request ch 12" in dialog.inner_text()
    assert "PW-RANGE-SENSOR" in dialog.inner_text()
