"""Named random streams derived from one seed, identical in every process.

The RSU process, the OBU process and the offline runner each draw from their own
stream, so a seed gives the same sensor noise live and offline.
"""

from __future__ import annotations

import numpy as np

STREAMS = ("rsu_camera", "lidar", "localization", "rsu_render", "ego_render", "rsu_sway")  # append only: indices seed the streams


def stream(seed: int, name: str, index: int = 0) -> np.random.Generator:
    """The generator of stream ``name`` for ``seed`` (independent of the other streams).
    ``index``: which of several like sensors (the k-th RSU or vehicle of a scenario); index 0
    is the stream a single-RSU, single-vehicle scenario has always drawn from."""
    if name not in STREAMS:
        raise ValueError(f"unknown random stream {name!r}; one of {STREAMS}")
    key = (STREAMS.index(name),) if index == 0 else (STREAMS.index(name), int(index))
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=key))
