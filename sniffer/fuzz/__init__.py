"""``whiztap fuzz server``'s running half: sessions over sockets, the server
kept alive, findings shrunk and written (docs/fuzz.md).  What to send and how
to judge it is ``whiztap.analyzer.fuzz``'s."""
