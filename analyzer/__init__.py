"""whiztap's protocol knowledge: framing, decoding, rules and the session model (sans-IO)."""

__version__ = "0.1.0"
