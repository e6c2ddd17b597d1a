"""The monitor: a sink that mirrors every pipeline key into rerun (the only place rerun is called)."""
