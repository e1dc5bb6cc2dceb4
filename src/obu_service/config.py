"""OBU service configuration (YAML + CLI overrides, validated at start-up)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator, model_validator

from v2i.runtime.config import ServiceConfig
from v2i.runtime.site import Site, check_site_or_scenario, lane_predictor
from v2i.security.pki import PkiError
from v2i.security.pki_registry import certified_rsus
from schemas.keys import check_id

from obu_service.methods import check_fusion
from obu_service.pipeline import COMPENSATIONS, FUSION_METHODS, FUSION_MODES, ObuPipelineConfig
from obu_service.rsu_table import MAX_RSUS


def site_position(site: Site, rsu_id: str) -> tuple[float, float] | None:
    """Where RSU ``rsu_id`` stands on ``site``: the site's RSU of that id, or the only RSU of a
    single-RSU site whatever the id (as an RSU service of that id runs it: ``Site.rsu``); None
    when the site cannot place it."""
    try:
        return site.rsu(rsu_id).xy
    except ValueError:
        return None


class ObuConfig(ServiceConfig):
    vehicle_id: str = "ego"
    site: str | None = Field(None, description="site file (v2i.runtime.site): the RSUs, vehicles, map origin "
                             "and map this OBU runs in, instead of a scenario's; with source zenoh")
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7448"])
    fusion: Literal[(*FUSION_METHODS, "roif")] = Field("kf", description="object-level method, or roif: "
                                                       "image-level fusion of the ego camera with the RSU's "
                                                       "image features (Maqsud's thesis; obu_service.image_fusion)")
    source: Literal["sim", "zenoh"] = Field("sim", description="own detections and pose: sim, the scenario's "
                                            "LiDAR and localisation sampled in the OBU; zenoh: received on "
                                            "v2x/sensor/vehicle/{vehicle_id}/objects|pose (e.g. from v2i world)")
    compensation: Literal[COMPENSATIONS] = "predict"
    fusion_mode: Literal[FUSION_MODES] = Field("adaptive", description="which RSU data a cycle fuses (IAAD, Liu et al.)")
    iou_threshold: float = Field(0.1, gt=0, le=1)
    inter_max_age_s: float = Field(0.6, gt=0, le=30, description="inter-frame fusion uses RSU data up to this old")
    planning_max_age_s: float = Field(5.0, gt=0, le=60, description="planning fusion uses RSU paths up to this old")
    max_clock_uncertainty_ms: float = Field(50.0, ge=0, le=60_000, description="intra and inter fuse an RSU's "
                                            "lists only while its stated clock uncertainty is at most this "
                                            "(1.5 m allowed / 30 m/s fastest = 50 ms; ObuPipelineConfig)")
    planning_max_clock_uncertainty_ms: float = Field(500.0, ge=0, le=60_000, description="planning uses an RSU's "
                                                     "paths only while its stated clock uncertainty is at most this")
    deadline_ms: float = Field(100.0, gt=0, le=10_000, description="end-to-end: own LiDAR capture -> fused output")
    output_interval_ms: float = Field(150.0, gt=0, le=10_000, description="longest allowed gap between two outputs")
    fuse_delay_ms: float = Field(50.0, ge=0, le=10_000, description="own perception latency: LiDAR capture -> fusion")
    sync_rate_hz: float = Field(10.0, gt=0, le=100)
    time_query_timeout_s: float = Field(60.0, gt=0, le=600, description="replies later than this are lost "
                                        "(a buffering cellular link can deliver tens of seconds late)")
    # admission of RSU input (obu_service.pipeline module docstring)
    known_rsus: dict[str, tuple[float, float] | None] | None = Field(
        None, description="the registered RSUs (--known-rsus ID,ID): a list of ids, or id -> map position (m); "
                          "an id without one stands where the site places it (its RSU of that id, or a single-RSU "
                          "site's only RSU). Registered RSUs are served first by the intake, always admitted, and "
                          "their objects bounded by site_radius_m around them (default: the site's RSUs and the "
                          "RSU ids the pki_dir's certificates certify that the site places; ObuConfig.registration)")
    accept_unknown_rsus: bool = Field(True, description="admit RSU ids outside known_rsus (bounded)")
    max_unknown_rsus: int = Field(16, ge=0, le=64)
    rsu_expiry_s: float = Field(30.0, gt=0, le=3600, description="an RSU not heard this long is forgotten")
    site_radius_m: float = Field(2000.0, gt=0, le=100_000, description="RSU objects farther from their RSU "
                                 "(or, for an unknown one, from the ego) are dropped")
    max_objects_per_list: int = Field(256, ge=1, le=1024)
    max_rsu_objects_per_cycle: int = Field(1024, ge=1, le=100_000)
    max_prediction_s: float = Field(1.0, ge=0, le=10, description="an RSU list predicted further ahead is refused")
    max_path_points: int = Field(8192, ge=1, le=1 << 20, description="predicted positions in one prediction list")
    future_tolerance_ms: float = Field(20.0, ge=0, le=10_000, description="RSU data may be stamped this much "
                                       "(plus the clock uncertainty) after its arrival")
    v2v: bool = Field(False, description="V2V: share own perception on v2x/v2v/{vehicle_id}/objects and fuse "
                      "peers' (obu_service.peers), through the V2V emulator")
    max_peers: int = Field(8, ge=1, le=32, description="V2V peers given a fusion source slot")
    wires: tuple[Literal["v2i", "cpm", "sdsm"], ...] = Field(
        ("v2i",), min_length=1, description="RSU list encodings subscribed to (RSU --wire): v2i, and the standard "
        "cpm / sdsm, whose ASN.1 is compiled at start-up (~0.3 s of CPU, before the service is ready)")
    # the node's intake (v2i.runtime.intake)
    max_message_bytes: int = Field(262_144, ge=1024, le=1 << 20, description="larger payloads are refused unread")
    source_rate_hz: float = Field(50.0, gt=0, le=10_000, description="messages per second accepted per key")
    source_burst: int = Field(25, ge=1, le=10_000)
    inbox_capacity: int = Field(512, ge=8, le=100_000, description="queued messages, all keys together")
    inbox_max_bytes: int = Field(4 << 20, ge=1 << 20, le=1 << 30, description="their bytes")
    input_guard_ms: float = Field(15.0, ge=0, le=1000, description="no large input is started this close to "
                                  "the next timed step (the longest decode of an admitted message)")
    # signed RSU messages (obu_service.inbound_security)
    pki_dir: str | None = Field(None, description="site PKI directory (v2i pki): the CA, revocation list and "
                                "known certificates RSU messages are verified against")
    security: Literal["strict", "permissive", "off"] | None = Field(
        None, description="strict drops unsigned, forged, unknown, revoked, expired, wrong-key, stale and replayed "
        "RSU messages; permissive counts them and fuses them anyway; off unwraps without checking "
        "(default: strict with pki_dir, off without)")

    # image-level fusion (fusion roif; obu_service.image_fusion)
    roif_pair_tolerance_ms: float = Field(50.0, ge=0, le=1000, description="an RSU frame pairs with an ego "
                                          "camera frame when their capture times differ by at most this")
    roif_wait_ms: float = Field(300.0, ge=0, le=10_000, description="an ego frame waits this long for its "
                                "RSU partner (RSU processing + link), then goes out with its own boxes only")
    roif_deadline_ms: float = Field(450.0, gt=0, le=10_000, description="ego camera capture -> image output; "
                                    "later is a deadline miss")
    roif_max_age_ms: float = Field(2000.0, gt=0, le=60_000, description="RSU frames older on arrival are stale")
    roif_model: str | None = Field(None, description="ONNX detector of the ego camera (default: the shipped one)")
    roif_threads: int | None = Field(None, ge=1, le=256, description="ONNX Runtime threads of the ego camera")

    @field_validator("known_rsus", mode="before")
    @classmethod
    def _ids_or_positions(cls, v):
        """A list of ids (``--known-rsus``, YAML ``[rsu1, rsu2]``) as ids without a position."""
        if isinstance(v, (list, tuple)) and all(isinstance(rsu_id, str) for rsu_id in v):
            if len(set(v)) != len(v):
                raise ValueError(f"an RSU id given twice: {list(v)}")
            return dict.fromkeys(v)
        return v

    @field_validator("known_rsus")
    @classmethod
    def _valid_rsu_ids(cls, v: dict[str, tuple[float, float] | None] | None):
        for rsu_id in v or {}:
            check_id(rsu_id)
        return v

    @field_validator("vehicle_id")
    @classmethod
    def _valid_id(cls, v: str) -> str:
        return check_id(v)

    @model_validator(mode="after")
    def _checks_need_a_pki(self) -> "ObuConfig":
        if self.security in ("strict", "permissive") and self.pki_dir is None:
            raise ValueError(f"security {self.security!r} needs pki_dir (--pki DIR): the site CA to verify against")
        return self

    @property
    def security_policy(self) -> str:
        """The policy in force: ``security``, or strict with a PKI and off without."""
        return self.security or ("strict" if self.pki_dir else "off")

    @model_validator(mode="after")
    def _clock_bounds_ordered(self) -> "ObuConfig":
        if self.max_clock_uncertainty_ms > self.planning_max_clock_uncertainty_ms:
            raise ValueError(f"max_clock_uncertainty_ms ({self.max_clock_uncertainty_ms}) exceeds "
                             f"planning_max_clock_uncertainty_ms ({self.planning_max_clock_uncertainty_ms}): "
                             "planning's bound is the looser one")
        return self

    @model_validator(mode="after")
    def _method_fits_compensation(self) -> "ObuConfig":
        if self.fusion != "roif":
            check_fusion(self.fusion, self.compensation)
        return self

    @model_validator(mode="after")
    def _site_or_scenario(self) -> "ObuConfig":
        check_site_or_scenario(self, "OBU", ("zenoh",))
        return self

    def lanes(self, site: Site):
        """The site map's lane predictor when the ``lane`` compensation needs it, else None;
        ValueError when it needs one and the site has no map."""
        if self.compensation != "lane":
            return None
        if site.map is None:
            raise ValueError(f"compensation 'lane' needs a Lanelet2 map, and site {site.name!r} has none (a site "
                             "file names one as map:, a scenario has <scenario>.osm beside its YAML)")
        return lane_predictor(site)

    def registered_rsus(self, site: Site) -> dict[str, tuple[float, float]]:
        """RSU id -> map position (m) of the RSUs registered on ``site`` (``registration``)."""
        return self.registration(site, self.certified_rsus())

    def certified_rsus(self) -> dict[str, Path]:
        """RSU id -> certificate file, for the RSU ids the ``pki_dir`` certifies (``v2i.security.pki_registry``;
        {} without one); ValueError naming a file that cannot be read."""
        if self.pki_dir is None:
            return {}
        try:
            return certified_rsus(self.pki_dir)
        except PkiError as exc:
            raise ValueError(str(exc)) from None

    def registration(self, site: Site, certified: dict[str, Path]) -> dict[str, tuple[float, float]]:
        """RSU id -> map position (m) of the RSUs this OBU registers on ``site``, in order, ``certified``
        being ``certified_rsus()``:

        - ``known_rsus`` when given (``--known-rsus``): exactly those, each at its own position or where
          the site places it (``site_position``); ValueError for one the site cannot place;
        - else the site's RSUs, then each RSU the PKI certifies that the site places (on a single-RSU site:
          whatever id ``v2i rsu`` runs as, e.g. the README's ``rsu1`` on a scenario whose RSU is ``rsu-nw``),
          while RSU slots are left (``MAX_RSUS`` less the unknown RSUs' and the V2V peers').

        Those the PKI certifies and this leaves out the OBU names at start (``obu_service.cli``)."""
        if self.known_rsus is not None:
            return {rsu_id: self._known_position(site, rsu_id, xy) for rsu_id, xy in self.known_rsus.items()}
        rsus = site.rsu_positions()
        room = MAX_RSUS - len(rsus) - (self.max_unknown_rsus if self.accept_unknown_rsus else 0) \
            - (self.max_peers if self.v2v else 0)
        for rsu_id in certified:
            xy = site_position(site, rsu_id)
            if rsu_id not in rsus and xy is not None and room > 0:
                rsus[rsu_id], room = xy, room - 1
        return rsus

    @staticmethod
    def _known_position(site: Site, rsu_id: str, xy: tuple[float, float] | None) -> tuple[float, float]:
        """``xy``, or where ``site`` places ``rsu_id``; ValueError when neither says."""
        xy = xy if xy is not None else site_position(site, rsu_id)
        if xy is None:
            raise ValueError(f"known_rsus: site {site.name!r} has no RSU {rsu_id!r} (its RSUs: "
                             f"{[r.id for r in site.rsus]}) to place it at: give its map position "
                             f"(known_rsus: {{{rsu_id}: [x, y]}} in --config) or a site that lists it")
        return xy

    def own_size_m(self, site: Site) -> tuple[float, float]:
        """Length, width (m) of this vehicle: the site's vehicle of this id, else its first."""
        size = site.vehicle(self.vehicle_id).size_m
        return size[0], size[1]

    def pipeline_config(self, site: Site) -> ObuPipelineConfig:
        """The pipeline's configuration on ``site`` (its RSUs registered, this vehicle's size)."""
        return ObuPipelineConfig(
            vehicle_id=self.vehicle_id, fusion=self.fusion, compensation=self.compensation,
            fusion_mode=self.fusion_mode, iou_threshold=self.iou_threshold, inter_max_age_s=self.inter_max_age_s,
            planning_max_age_s=self.planning_max_age_s, deadline_ms=self.deadline_ms,
            max_clock_uncertainty_ms=self.max_clock_uncertainty_ms,
            planning_max_clock_uncertainty_ms=self.planning_max_clock_uncertainty_ms,
            output_interval_ms=self.output_interval_ms, known_rsus=self.registered_rsus(site),
            accept_unknown_rsus=self.accept_unknown_rsus, max_unknown_rsus=self.max_unknown_rsus,
            rsu_expiry_s=self.rsu_expiry_s, site_radius_m=self.site_radius_m,
            max_objects_per_list=self.max_objects_per_list, max_rsu_objects_per_cycle=self.max_rsu_objects_per_cycle,
            max_prediction_s=self.max_prediction_s, max_path_points=self.max_path_points,
            future_tolerance_ms=self.future_tolerance_ms, ego_size_m=self.own_size_m(site),
        )
