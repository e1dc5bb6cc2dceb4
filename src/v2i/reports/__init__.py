"""Reports of a run: pictures (matplotlib) and the chaos summary."""
