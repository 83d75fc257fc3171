"""Running probes over sockets and processes: the cases of ``whiztap.analyzer.probe`` against a live peer."""
