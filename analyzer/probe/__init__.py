"""Active conformance testing (``whiztap probe``): the cases, their schedules and
verdicts, sans-IO; ``whiztap.sniffer.probe`` runs them against a live peer."""
