"""Named random streams derived from one seed, identical in every process.

The RSU process, the OBU process and the offline runner each draw from their own
stream, so a seed gives the same sensor noise live and offline.
"""

from __future__ import annotations

import numpy as np

STREAMS = ("rsu_camera", "lidar", "localization", "rsu_render", "ego_render", "rsu_sway")  # append only: indices seed the streams


def stream(seed: int, name: str) -> np.random.Generator:
    """The generator of stream ``name`` for ``seed`` (independent of the other streams)."""
    if name not in STREAMS:
        raise ValueError(f"unknown random stream {name!r}; one of {STREAMS}")
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(STREAMS.index(name),)))
