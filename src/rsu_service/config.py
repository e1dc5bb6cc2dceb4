"""RSU service configuration (YAML + CLI overrides, validated at start-up)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from v2i.runtime.config import ServiceConfig
from v2i.runtime.site import check_site_or_scenario
from schemas.keys import check_id
from schemas.list_wire import WIRES

PREDICTORS = ("auto", "lane", "cv")  # long-horizon path predictors, see rsu_service.prediction
SOURCES = ("sim", "camera", "video", "zenoh")  # perception sources, see rsu_service.source


class RsuConfig(ServiceConfig):
    rsu_id: str = Field("rsu1", description="the id in its key expressions (v2x/rsu/{rsu_id}/*) and, by default, "
                        "the certificate it signs with; the site's RSU of that id, or a single-RSU site's only RSU "
                        "whatever the id (Site.rsu). An OBU registers it from its site, its pki_dir's certificate of "
                        "this id, or its known_rsus (ObuConfig.registration)")
    site: str | None = Field(None, description="site file (v2i.runtime.site): the RSUs, vehicles, map origin "
                             "and map this RSU runs in, instead of a scenario's; with source zenoh or video")
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    clock_offset_ms: float = Field(0.0, ge=-86_400_000, le=86_400_000)
    clock_drift_ppm: float = Field(0.0, ge=-1000, le=1000)
    clock_step_ms: float = Field(0.0, ge=-86_400_000, le=86_400_000)
    clock_step_at_s: float | None = Field(None, ge=0, description="scenario time of the clock step")
    predictor: Literal[PREDICTORS] = Field("auto", description="long-horizon paths: lane (Lanelet2 map), cv, or auto "
                                               "(lane when the site has a map)")
    wire: Literal[WIRES] = Field("v2i", description="object list encoding: v2i (msgpack columns on "
                                 "v2x/rsu/{id}/objects), cpm (ETSI CPM, UPER, on .../cpm) or sdsm (SAE J3224 SDSM, "
                                 "UPER, on .../sdsm: J3224's fields, not its bytes, docs/messages.md); see schemas.list_wire")
    cpm_rules: bool = Field(False, description="with wire cpm: ETSI TS 103 324 generation rules (an object goes "
                            "when new, moved > 4 m, speed changed > 0.5 m/s, heading > 4 degrees, or 1 s since last "
                            "sent; pedestrians and cyclists every 500 ms) and segmentation to cpm_mtu_bytes; see "
                            "rsu_service.cpm_rules (off: every object in every list, one CPM)")
    cpm_mtu_bytes: int = Field(1100, ge=200, le=65_535, description="with cpm_rules: a larger CPM is split into "
                               "segments (segmentationInfo, at most 8) of at most this many bytes (default: TR 103 "
                               "562's 1100 B)")
    predict_ahead: bool = Field(False, description="track-predict: publish tracks predicted to the publish "
                                                   "time and upsample 5 Hz to 10 Hz (Saravanan et al. Algorithm 1)")
    source: Literal[SOURCES] = Field("sim", description="sim: the scenario's camera noise model (fast); camera: "
                                     "the world rendered, through the ONNX detector and the calibration; video: "
                                     "a video file or image folder (--video) through the same; zenoh: SensorObjects received on "
                                     "v2x/sensor/rsu/{rsu_id}/objects (e.g. from v2i world)")
    video: str | None = Field(None, description="with source video: a video file or a folder of PNG/JPEG images")
    rate_hz: float | None = Field(None, gt=0, le=100, description="with source video: frames per second "
                                  "(default: the video's, 10 for a folder); with source camera: the camera's "
                                  "rate (default: the scenario's RSU rate)")
    image_features: bool = Field(False, description="with source camera or video: also publish each frame's "
                                 "boxes + ORB features on v2x/rsu/{id}/image_features (ROIF, Maqsud's thesis)")
    image_features_max: int = Field(1000, ge=1, le=4096, description="ORB keypoints per frame at most in "
                                    "image_features (the strongest; ~42 bytes each on the wire)")
    model: str | None = Field(None, description="ONNX detector (YOLOv8/v5 export layout, e.g. a COCO YOLOv8n "
                              "export for real images; default: the shipped model, trained on rendered frames of "
                              "the bundled scenes only)")
    calibration: str | None = Field(None, description="calibration file (v2i camera calibrate); default: the "
                                    "scenario's shipped one")
    detector_threads: int | None = Field(None, ge=1, le=256, description="ONNX Runtime intra-op threads")
    score_threshold: float = Field(0.4, gt=0, lt=1, description="detector score threshold (0.3 let a facade "
                                   "texture 76 m out through as a pedestrian in 79 of 150 red-light-runner frames)")
    input_max_objects: int = Field(1024, ge=1, le=1024, description="with source zenoh: frames with more "
                                   "detections are refused")
    input_max_age_ms: float = Field(1000.0, gt=0, le=60_000, description="with source zenoh: frames captured "
                                    "longer before their receipt are refused (stale)")
    input_future_ms: float = Field(20.0, ge=0, le=10_000, description="with source zenoh: frames stamped "
                                   "this much after their receipt are refused (the sensor shares this host's clock)")
    input_max_bytes: int = Field(262_144, ge=1024, le=1 << 20, description="with source zenoh: larger "
                                 "payloads are refused unread")
    query_rate_hz: float = Field(2000.0, gt=0, le=100_000, description="time queries read per second, all "
                                 "queriers together; more are refused unread")
    query_burst: int = Field(500, ge=1, le=100_000)
    querier_rate_hz: float = Field(50.0, gt=0, le=100_000, description="time queries answered per second "
                                   "and querier (obu_id), so a flood under one name does not starve the others")
    querier_burst: int = Field(20, ge=1, le=100_000)
    max_query_bytes: int = Field(1024, ge=64, le=1 << 20, description="larger time queries are refused unread")
    pki_dir: str | None = Field(None, description="site PKI directory (v2i pki): sign object lists, prediction "
                                "lists, image features and time replies with <identity>.key / .cert from it")
    identity: str | None = Field(None, description="the certificate subject to sign as (default: rsu_id)")
    save_wire: str | None = Field(None, description="save every object list sent, as sent (before any signature), "
                                  "one file per list: <save_wire>/<rsu_id>/<6-digit index in send order>.<wire>."
                                  "<msgpack|uper> (v2i.runtime.wire_files)")

    @field_validator("rsu_id")
    @classmethod
    def _valid_id(cls, v: str) -> str:
        return check_id(v)

    @model_validator(mode="after")
    def _site_or_scenario(self) -> "RsuConfig":
        check_site_or_scenario(self, "RSU", ("zenoh", "video"))
        if self.cpm_rules and self.wire != "cpm":
            raise ValueError(f"cpm_rules (--cpm-rules) applies to wire cpm, not {self.wire}")
        return self

    @property
    def skewed_clock(self) -> bool:
        """Whether the RSU's clock is offset, drifts or steps on purpose (the clock_* fields)."""
        return bool(self.clock_offset_ms or self.clock_drift_ppm
                    or (self.clock_step_ms and self.clock_step_at_s is not None))

