"""Active conformance testing (``whiztap probe``) and fuzzing (``whiztap fuzz``):
the cases, mutations and verdicts, sans-IO; ``whiztap.sniffer.probe`` and
``whiztap.sniffer.fuzz`` run them over sockets."""
