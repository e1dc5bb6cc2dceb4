"""Where a service's ``/metrics`` endpoint listens by default, and the start-up error when it cannot.

Shared by the options (``v2i.telemetry.metrics_cli``, light: no ``prometheus_client``) and the
exporter (``v2i.telemetry.prometheus``), so that neither imports the other's module for them.
"""

DEFAULT_ADDRESS = "127.0.0.1"


class MetricsPortError(ValueError):
    """The exporter cannot listen where it was told (port in use, bad address): a start-up error."""
