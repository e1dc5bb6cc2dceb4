"""Telemetry of the services: per-stage latency (``latency``), exporters and snapshots (pure or thin I/O)."""
