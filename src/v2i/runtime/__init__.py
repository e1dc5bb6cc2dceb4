"""Service runtime: Zenoh sessions (transport), intake queues, config loading, process conventions, sensor screens."""
