"""The recording's two compiled-library questions, measured side by side in one run.

* MCAP writing: whiztap's own writer (``analyzer/recording/mcap.py``: one
  struct pack per message into the open chunk, zstd per chunk) against the
  Foxglove SDK's Rust writer (``foxglove.open_mcap`` and ``Channel.log``), on
  the recorder's commonest message (a /tcp/reads message of one 16-byte
  frame), as many messages per call as a TCP read gives (4), zstd, 1 MiB
  chunks.  The one that writes faster writes whiztap's files.
* JSON: the standard library's encoder (as the recorder uses it) against
  orjson and msgspec, on a /violations message, the commonest message the
  recorder still builds as a dict.

Prints messages per second for each and the ratios.
"""

from __future__ import annotations

import json
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

MESSAGES = 300_000
PER_CALL = 4
ROUNDS = 3
READ = (b'{"conn":1,"dir":"c2s","t_ns":1700000000000000000,"offset":123456,"size":16,'
        b'"data":"cnIxLTEyLS0wLS0wLXNzMQ=="}')
VIOLATION = {"conn": 1, "t_ns": 1700000000000000000, "rule_id": "FR-CHANNEL-RANGE", "severity": "error",
             "level": 3, "section": "4.2", "summary": "channel out of range",
             "detail": "channel 99 is outside 1-64", "dir": "c2s", "frame_index": 1234,
             "frame_text": "rr1-99--0--0-ss1"}


def _ours(path: Path) -> float:
    from whiztap.analyzer.recording.mcap import McapWriter

    with open(path, "wb") as f:
        writer = McapWriter(f, chunk_size=1 << 20, compression="zstd")
        writer.start("whiztap-bench", "bench")
        schema = writer.register_schema("s", "jsonschema", b"{}")
        channel = writer.register_channel("/tcp/reads", "json", schema)
        add = writer.add_messages
        start = time.perf_counter()
        for i in range(0, MESSAGES, PER_CALL):
            add([(channel, 1_700_000_000_000_000_000 + i + k, READ) for k in range(PER_CALL)])
        writer.finish()
    return MESSAGES / (time.perf_counter() - start)


def _foxglove(path: Path) -> float:
    import foxglove
    from foxglove.mcap import MCAPCompression, MCAPWriteOptions

    context = foxglove.Context()
    options = MCAPWriteOptions(compression=MCAPCompression.Zstd, chunk_size=1 << 20)
    writer = foxglove.open_mcap(str(path), allow_overwrite=True, context=context, writer_options=options)
    channel = foxglove.Channel("/tcp/reads", message_encoding="json", context=context,
                               schema=foxglove.Schema(name="s", encoding="jsonschema", data=b"{}"))
    log = channel.log
    start = time.perf_counter()
    for i in range(0, MESSAGES, PER_CALL):
        for k in range(PER_CALL):
            log(READ, log_time=1_700_000_000_000_000_000 + i + k)
    writer.close()
    return MESSAGES / (time.perf_counter() - start)


def _encoders() -> dict[str, Callable[[dict], bytes]]:
    import msgspec
    import orjson

    compact = json.JSONEncoder(separators=(",", ":")).encode
    return {"json (stdlib)": lambda m: compact(m).encode(), "orjson": orjson.dumps,
            "msgspec": msgspec.json.Encoder().encode}


def _json_rate(encode: Callable[[dict], bytes]) -> float:
    message = VIOLATION
    start = time.perf_counter()
    for _ in range(MESSAGES):
        encode(message)
    return MESSAGES / (time.perf_counter() - start)


def _best(measure: Callable[[], float]) -> float:
    return max(measure() for _ in range(ROUNDS))


def main() -> None:
    print("== recording writer and JSON (bench_writer) ==")
    with tempfile.TemporaryDirectory() as d:
        ours = _best(lambda: _ours(Path(d) / "ours.mcap"))
        sdk = _best(lambda: _foxglove(Path(d) / "sdk.mcap"))
    print(f"MCAP, {MESSAGES:,} read messages, best of {ROUNDS}: whiztap's writer {ours:,.0f}/s; "
          f"foxglove-sdk {sdk:,.0f}/s; ours / sdk {ours / sdk:.2f}")
    rates = {name: _best(lambda e=encode: _json_rate(e)) for name, encode in _encoders().items()}
    base = rates["json (stdlib)"]
    print("JSON, a /violations message: " + "; ".join(
        f"{name} {rate:,.0f}/s ({rate / base:.1f}x)" for name, rate in rates.items()))
