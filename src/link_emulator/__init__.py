"""Link emulator: seeded channel models and profiles (pure) plus the Zenoh relay process.

The relay is the only path between the RSU side and the vehicle side; it imposes a
``LinkProfile`` on every message it forwards: per direction delay + jitter (optionally
correlated), Bernoulli or Gilbert-Elliott loss, distance PDR and range, bandwidth and a
send queue, fifo order, duplication, outages and trace replay (``profile.py``,
``channel.py``). ``v2i link validate`` checks a profile's model against its declaration
(``validate.py``).
"""
