"""Input / output services: ``play`` (dataset -> frames), ``view`` (bus -> rerun), ``record`` (bus -> files)."""
