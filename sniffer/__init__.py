"""whiztap's socket side: the simulator, client, recording proxy and capture."""
