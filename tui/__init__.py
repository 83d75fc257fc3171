"""whiztap's terminal user interface."""
