"""The deterministic offline runner (v2i eval), what a run is, chaos timelines and the experiment tables."""
