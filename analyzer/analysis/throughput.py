"""Settings for bulk work over millions of frames."""

import gc


def tune_gc() -> None:
    """Collect young objects less often.

    Framing a large recording makes millions of small, short-lived tuples, and
    CPython's default threshold (700 allocations) runs the collector so often that
    it costs about as much as the work itself.  None of these objects form cycles,
    so batch commands (analyze, cat, benchmarks) and the recorder's writer
    process, which turns every frame into messages, raise the threshold and
    freeze what was loaded at start-up.  Interactive processes keep the
    defaults.
    """
    gc.freeze()
    gc.set_threshold(100_000, 50, 1000)
