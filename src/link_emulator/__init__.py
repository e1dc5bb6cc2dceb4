"""Link emulator: seeded channel models and profiles (pure) plus the Zenoh relay process.

The relay is the only path between the RSU side and the vehicle side; it imposes a
``LinkProfile`` (delay, jitter, loss per direction) on every message it forwards.
"""
