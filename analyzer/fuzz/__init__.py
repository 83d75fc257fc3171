"""Spec-aware fuzzing without sockets: sessions, mutations, shrinking, judging.

``whiztap fuzz server`` (docs/fuzz.md) plays hostile clients against a server.
Everything it *decides* lives here, as pure functions of a seeded
``random.Random`` and the facts of the protocol package: what a session is and
how one is generated from the message and handshake tables (``grammar``), the
mutation vocabulary (``mutate``), the corpus (``corpus``), delta debugging
(``shrink``) and the verdict on what the server answered (``judge``, the
analyzer's own ``Session``).  What *does* it, over sockets and with a clock,
is ``whiztap.sniffer.fuzz``; keeping the split means a seed decides every
execution, whatever the machine.
"""
