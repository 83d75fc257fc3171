"""Fleet runs (docs/fleet.md): per-file tasks on a Dask cluster, for ``analyze --dask``."""
