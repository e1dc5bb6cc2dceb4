"""Link emulator configuration: one frozen model, loaded from YAML plus CLI overrides."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, FiniteFloat

# <protocol>/<address>[?<metadata>][#<config>], e.g. tcp/127.0.0.1:7447 or udp/[::1]:7447
Endpoint = Annotated[str, Field(pattern=r"^[A-Za-z0-9_-]+/\S+$")]


class LinkConfig(BaseModel):
    """Where the emulator connects and which profile it imposes.

    ``rsu_connect`` and ``vehicle_connect`` are Zenoh endpoints (e.g. ``tcp/10.0.0.1:7447``)
    of the two sides; the emulator opens one session per side and is their only path.
    ``rsu_position`` (map frame, m) lets the channel model depend on the vehicle-RSU
    distance, the vehicle's position coming from its published ego pose.
    ``control_listen``: endpoints the vehicle-side session also listens on, for controllers
    (``v2i link set``, ``v2i chaos run``) that put ``LinkControl`` on ``v2x/link/{link_id}/control``
    and read the stats there; Zenoh peers do not forward, so a controller must reach the
    emulator directly.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    link_id: str = Field(default="link1", pattern=r"^[A-Za-z0-9_-]{1,64}$", description="names v2x/link/{link_id}/*")
    rsu_connect: list[Endpoint] = Field(min_length=1, description="Zenoh endpoints of the RSU side")
    vehicle_connect: list[Endpoint] = Field(min_length=1, description="Zenoh endpoints of the vehicle side")
    control_listen: list[Endpoint] = Field(
        default_factory=list, description="extra Zenoh endpoints to listen on for link controllers"
    )
    profile: str = Field(default="lte-v2x", min_length=1, description="bundled profile name or YAML path")
    seed: int = Field(default=0, ge=0, description="seed of the channel draws")
    stats_period_s: float = Field(default=1.0, gt=0.0, description="period of the stats publication in s")
    rsu_position: tuple[FiniteFloat, FiniteFloat] | None = Field(
        default=None, description="RSU antenna [x, y] in the map frame (m); None: distance unknown"
    )
    vehicle_id: str | None = Field(default=None, pattern=r"^[A-Za-z0-9_-]{1,64}$", description="the vehicle whose "
                                   "ego poses set the distance (default: the first one heard)")
    # bounds on what peers can make the emulator hold (relay.Gate); refusals are counted in the stats
    max_message_bytes: int = Field(default=1 << 20, ge=1024, le=64 << 20, description="larger payloads are refused")
    source_rate_hz: float = Field(default=100.0, gt=0.0, description="messages per second accepted per key "
                                  "(a V2X source sends at most tens)")
    source_burst: int = Field(default=50, ge=1)
    total_bytes_per_s: float = Field(default=16e6, gt=0.0, description="bytes per second accepted from all keys "
                                     "together (more than any V2X radio carries)")
    max_pending_arrivals: int = Field(default=512, ge=16, description="received, not yet drawn through the channel")
    max_in_flight: int = Field(default=100_000, ge=16, description="messages scheduled for delivery, per direction")
    max_in_flight_bytes: int = Field(default=64 << 20, ge=1 << 16, description="their bytes, per direction")
    max_open_queries: int = Field(default=1024, ge=1, description="vehicle time queries kept open")
