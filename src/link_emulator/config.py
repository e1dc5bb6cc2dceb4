"""Link emulator configuration: one frozen model, loaded from YAML plus CLI overrides."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, FiniteFloat, model_validator

# <protocol>/<address>[?<metadata>][#<config>], e.g. tcp/127.0.0.1:7447 or udp/[::1]:7447
Endpoint = Annotated[str, Field(pattern=r"^[A-Za-z0-9_-]+/\S+$")]
VehicleId = Annotated[str, Field(pattern=r"^[A-Za-z0-9_-]{1,64}$")]

# RSU-vehicle pairs one emulator serves: each costs a Zenoh session, a channel model and a
# stats entry (published every period), so the number is bounded; a V2X radio cell rarely
# serves more vehicles at once.
MAX_VEHICLES = 64


class VehicleLinkConfig(BaseModel):
    """One vehicle served by the emulator: its id (names ``v2x/obu/{vehicle_id}/*``) and the
    Zenoh endpoints of its side, reached by a session of its own (``--vehicle ID=EP[,EP]``)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    vehicle_id: VehicleId
    connect: list[Endpoint] = Field(min_length=1, description="Zenoh endpoints of this vehicle's side")


class VehicleSide(BaseModel):
    """A vehicle side as the relay opens it: ``vehicle_id`` None means "the first one heard"."""

    model_config = ConfigDict(frozen=True)

    vehicle_id: str | None
    connect: list[str]


class LinkConfig(BaseModel):
    """Where the emulator connects and which profile it imposes.

    ``rsu_connect`` are the Zenoh endpoints (e.g. ``tcp/10.0.0.1:7447``) of the RSU side; the
    vehicle sides are either ``vehicle_connect`` (one vehicle, ``vehicle_id`` or the first id
    heard, seeded by ``seed`` itself) or ``vehicles`` (each its own id, endpoints, session and
    channel, seeded by ``seed`` and its id). The emulator opens one session per side and is
    their only path. ``rsu_position`` (map frame, m) lets the channel model depend on the
    vehicle-RSU distance, each vehicle's position coming from its published ego pose.
    ``control_listen``: endpoints a control session of the emulator listens on, for controllers
    (``v2i link set``, ``v2i chaos run``) that put ``LinkControl`` on ``v2x/link/{link_id}/control``
    and read the stats there; Zenoh peers do not forward, so a controller must reach the
    emulator directly. Control is authenticated (``pki``), refused (default) or, in the lab,
    accepted unsigned (``insecure_control``): see ``control_auth``.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    link_id: str = Field(default="link1", pattern=r"^[A-Za-z0-9_-]{1,64}$", description="names v2x/link/{link_id}/*")
    rsu_connect: list[Endpoint] = Field(default_factory=list, description="Zenoh endpoints of the RSU side "
                                        "(required, except in the V2V mode)")
    v2v: bool = Field(default=False, description="V2V mode: no RSU side; relay each vehicle's v2x/v2v/{id}/** to "
                      "every other vehicle through a channel per ordered vehicle pair (``v2v_relay``)")
    vehicle_connect: list[Endpoint] = Field(default_factory=list, description="Zenoh endpoints of the one "
                                            "vehicle side (one-vehicle form; else ``vehicles``)")
    vehicles: list[VehicleLinkConfig] = Field(default_factory=list, description="the vehicles served, each on its "
                                              f"own session and channel (at most {MAX_VEHICLES})")
    control_listen: list[Endpoint] = Field(
        default_factory=list, description="extra Zenoh endpoints to listen on for link controllers"
    )
    pki: str | None = Field(default=None, min_length=1, description="site PKI directory (v2i pki): link control "
                            "must be signed by an operator certificate of its CA (``control_auth``)")
    insecure_control: bool = Field(default=False, description="lab only: accept unsigned link control (without "
                                   "pki and without this, every control is refused)")
    control_max_age_s: float = Field(default=2.0, gt=0.0, le=60.0, description="signed control generated longer "
                                     "before its receipt (emulator clock) is refused as stale")
    control_max_ahead_s: float = Field(default=0.5, ge=0.0, le=60.0, description="signed control generated longer "
                                       "after its receipt (emulator clock) is refused as future")
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

    @model_validator(mode="after")
    def _one_vehicle_form(self) -> LinkConfig:
        """Either ``vehicle_connect`` (one vehicle) or ``vehicles`` (up to MAX_VEHICLES, ids unique);
        an RSU side, except in the V2V mode (``vehicles`` only, at least two, no RSU side)."""
        if self.pki is not None and self.insecure_control:
            raise ValueError("give either pki (--pki DIR: signed link control) or insecure_control "
                             "(--insecure-control: unsigned, lab only), not both")
        if self.v2v and (self.rsu_connect or self.vehicle_connect or len(self.vehicles) < 2):
            raise ValueError("v2v (--v2v) relays between vehicles only: give at least two vehicles as vehicles "
                             "(--vehicle ID=EP[,EP]) and no rsu_connect or vehicle_connect")
        if not self.v2v and not self.rsu_connect:
            raise ValueError("rsu_connect (--rsu-connect): at least one Zenoh endpoint of the RSU side")
        if bool(self.vehicle_connect) == bool(self.vehicles):
            raise ValueError("give the vehicle side(s) either as vehicle_connect (one vehicle, --vehicle-connect) "
                             "or as vehicles (--vehicle ID=EP[,EP], repeatable), exactly one of them")
        if len(self.vehicles) > MAX_VEHICLES:
            raise ValueError(f"vehicles: {len(self.vehicles)} given, one emulator serves at most {MAX_VEHICLES} "
                             "(run one emulator per RSU, each for the vehicles in its range)")
        ids = [v.vehicle_id for v in self.vehicles]
        if len(set(ids)) != len(ids):
            raise ValueError(f"vehicles: vehicle ids must be unique, got {', '.join(sorted(i for i in set(ids) if ids.count(i) > 1))} twice")
        if self.vehicles and self.vehicle_id is not None:
            raise ValueError("vehicle_id (--vehicle-id) belongs to the one-vehicle form; each entry of vehicles "
                             "names its own")
        return self

    def vehicle_sides(self) -> list[VehicleSide]:
        """The vehicle sides to open, in configured order (one for the one-vehicle form)."""
        if self.vehicle_connect:
            return [VehicleSide(vehicle_id=self.vehicle_id, connect=list(self.vehicle_connect))]
        return [VehicleSide(vehicle_id=v.vehicle_id, connect=list(v.connect)) for v in self.vehicles]
