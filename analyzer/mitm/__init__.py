"""Faults whiztap puts into traffic on purpose, as a man in the middle: what to do to which frames."""
