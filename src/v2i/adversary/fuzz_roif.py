"""``v2i fuzz --target obu --fusion roif``: hostile ``RsuImageFeatures`` against an OBU fusing images.

Topology as ``fuzz_targets.ObuFuzz``: an RSU (camera source, ``--image-features``, clock offset
250 ms, 10 Hz, id of the scenario's RSU so that the OBU registers it) and the OBU
(``--fusion roif``) connected to it directly; the attacker's session reaches both. Scenario
roif-intersection. Normal output: one ``ImageFusedBoxes`` per ego camera frame (10 Hz), late
after the OBU's image deadline (450 ms from capture).

Hostile kinds (``FEATURE_KINDS``; payloads from ``FeatureHostile``, seeded):
malformed (random bytes, truncated, bit flips), wrong_type (another message's envelope),
unknown_keys (in the body or the box columns), non_finite (NaN / inf coordinates or scores),
out_of_image (a keypoint or box outside the image), oversized_counts (more than 256 boxes or
4096 keypoints, or a payload over the OBU's size limit), wrong_descriptor_length, bad_index
(a keypoint naming a box the frame does not have), absurd_times, and edge_valid: valid frames
on the genuine RSU's key, stamped like its own, that reach the pairing and the fusion (0
keypoints, keypoints in no box, boxes with no keypoints, duplicate boxes, 4096 keypoints of
random descriptors, 256 boxes). Specials: flood (one payload on one key), fake_id (valid frames
from unregistered ids), replay (captured genuine frames again: duplicates or stale).
"""

from __future__ import annotations

import itertools
import sys
import time

import msgpack
import numpy as np

from schemas import keys
from schemas.codec import CodecError, decode, encode
from schemas.image_messages import (
    DESCRIPTOR_BYTES,
    F4,
    MAX_BOXES,
    MAX_KEYPOINTS,
    U1,
    U2,
    ImageFusedBoxes,
    RsuImageFeatures,
    to_bytes,
)
from v2i.runtime.transport import free_tcp_endpoint
from v2i.sim.scenario import load_scenario

from v2i.adversary.fuzz import MS, VEHICLE_ID
from v2i.adversary.fuzz_targets import CLOCK_OFFSET_MS, REPLAY_AGE_NS, ObuFuzz

SCENARIO = "roif-intersection"
W, H = 1280, 720
POOL = 24  # distinct payloads per kind
IMAGE_DEADLINE_MS = 450.0  # the OBU's default roif deadline


class FeatureHostile:
    """Hostile ``RsuImageFeatures`` payloads around valid ones (pure, seeded)."""

    def __init__(self, rng: np.random.Generator, rsu_id: str):
        self.rng, self.rsu_id = rng, rsu_id

    def message(self, t_ns: int, n_boxes: int = 4, n_kp: int = 200, rsu_id: str | None = None,
                duplicate: bool = False, kp_in_boxes: bool = True) -> RsuImageFeatures:
        """A valid frame: random boxes (or one box ``n_boxes`` times), random keypoints and descriptors."""
        r = self.rng
        lo = r.uniform(0, [W - 200, H - 150], (1 if duplicate else n_boxes, 2))
        boxes = np.hstack([lo, lo + r.uniform(20, [200, 150], (len(lo), 2))])
        boxes = np.repeat(boxes, n_boxes, axis=0) if duplicate else boxes
        index = r.integers(0, max(n_boxes, 1), n_kp) if n_boxes else np.zeros(0, int)
        kp = (r.uniform(boxes[index, :2], boxes[index, 2:]) if kp_in_boxes and n_boxes
              else r.uniform(0, [W, H], (n_kp, 2)))
        n_kp = len(index)
        return RsuImageFeatures(
            rsu_id=rsu_id or self.rsu_id, seq=int(r.integers(1 << 40)), t_ns=t_ns, image_width=W, image_height=H,
            boxes={"n": n_boxes, "xyxy": to_bytes(boxes, F4), "score": to_bytes(r.uniform(0.3, 1, n_boxes), F4),
                   "cls": to_bytes(r.integers(0, 8, n_boxes), U1)},
            n_keypoints=n_kp, keypoints=to_bytes(kp[:n_kp], F4),
            descriptors=r.integers(0, 256, n_kp * DESCRIPTOR_BYTES, dtype=np.uint8).tobytes(),
            keypoint_box=to_bytes(index, U2))

    def valid(self, t_ns: int, **kw) -> bytes:
        return encode(self.message(t_ns, **kw))

    def _body(self, t_ns: int, **kw) -> dict:
        return msgpack.unpackb(self.valid(t_ns, **kw), raw=False)

    def _pack(self, envelope: dict) -> bytes:
        return msgpack.packb(envelope, use_bin_type=True)

    # --- kinds ---------------------------------------------------------------------------------
    def malformed(self, t_ns: int) -> bytes:
        data, c = self.valid(t_ns), int(self.rng.integers(3))
        if c == 0:
            return self.rng.bytes(int(self.rng.integers(0, 4096)))
        if c == 1:
            return data[: int(self.rng.integers(0, len(data)))]
        flipped = bytearray(data)
        for i in self.rng.integers(0, len(flipped), int(self.rng.integers(1, 8))):
            flipped[i] ^= 1 << int(self.rng.integers(8))
        return bytes(flipped)

    def wrong_type(self, t_ns: int) -> bytes:
        env = self._body(t_ns)
        env["t"] = str(self.rng.choice(["object_list", "image_fused_boxes", "time_reply"]))
        return self._pack(env)

    def unknown_keys(self, t_ns: int) -> bytes:
        env = self._body(t_ns)
        (env["d"]["boxes"] if self.rng.random() < 0.5 else env["d"])[str(self.rng.choice(["evil", "__class__"]))] = 1
        return self._pack(env)

    def non_finite(self, t_ns: int) -> bytes:
        env = self._body(t_ns)
        d, bad = env["d"], float(self.rng.choice([np.nan, np.inf, -np.inf]))
        col = str(self.rng.choice(["keypoints", "xyxy", "score"]))
        holder = d if col == "keypoints" else d["boxes"]
        values = np.frombuffer(holder[col], F4).copy()
        values[int(self.rng.integers(len(values)))] = bad
        holder[col] = values.tobytes()
        return self._pack(env)

    def out_of_image(self, t_ns: int) -> bytes:
        env = self._body(t_ns)
        d = env["d"]
        holder, col = (d, "keypoints") if self.rng.random() < 0.5 else (d["boxes"], "xyxy")
        values = np.frombuffer(holder[col], F4).copy()
        values[int(self.rng.integers(len(values)))] = float(self.rng.choice([-5.0, W + 50.0, 1e9]))
        holder[col] = values.tobytes()
        return self._pack(env)

    def oversized_counts(self, t_ns: int) -> bytes:
        c = int(self.rng.integers(3))
        if c == 0:  # more keypoints than any frame may carry, columns to match
            env = self._body(t_ns, n_boxes=2, n_kp=MAX_KEYPOINTS)
            d, k = env["d"], MAX_KEYPOINTS + 1 + int(self.rng.integers(1000))
            d["n_keypoints"], d["keypoints"] = k, b"\x00" * (8 * k)
            d["descriptors"], d["keypoint_box"] = b"\x00" * (DESCRIPTOR_BYTES * k), b"\x00" * (2 * k)
            return self._pack(env)
        if c == 1:  # more boxes than a frame may carry
            env = self._body(t_ns, n_boxes=MAX_BOXES, n_kp=10)
            b, n = env["d"]["boxes"], MAX_BOXES + 1 + int(self.rng.integers(100))
            b["n"], b["xyxy"], b["score"], b["cls"] = n, np.tile([1, 1, 5, 5], n).astype(F4).tobytes(), b"\x00" * (4 * n), b"\x01" * n
            return self._pack(env)
        return self.rng.bytes(int(self.rng.integers(300_000, 1_500_000)))  # over the OBU's 256 kB limit

    def wrong_descriptor_length(self, t_ns: int) -> bytes:
        env = self._body(t_ns)
        d = env["d"]
        d["descriptors"] = d["descriptors"][: -int(self.rng.integers(1, 33))] if self.rng.random() < 0.5 else d["descriptors"] + b"\x00"
        return self._pack(env)

    def bad_index(self, t_ns: int) -> bytes:
        env = self._body(t_ns)
        d = env["d"]
        index = np.frombuffer(d["keypoint_box"], U2).copy()
        index[int(self.rng.integers(len(index)))] = int(self.rng.choice([d["boxes"]["n"], 65535]))
        d["keypoint_box"] = index.tobytes()
        return self._pack(env)

    def absurd_times(self, t_ns: int) -> bytes:
        c = int(self.rng.integers(3))
        if c == 0:
            env = self._body(t_ns)
            env["d"]["t_ns"] = int(self.rng.choice([0, -1, 2**63 - 1]))
            return self._pack(env)
        return self.valid(t_ns + int(self.rng.choice([-3600, 3600])) * 10**9)  # stale or from the future

    def edge_valid(self, t_ns: int) -> bytes:
        """Valid frames that reach the fusion; stamped as the genuine RSU's (``t_ns`` its clock)."""
        c = int(self.rng.integers(6))
        kw = [dict(n_kp=0), dict(kp_in_boxes=False), dict(n_boxes=5, n_kp=0), dict(n_boxes=6, duplicate=True),
              dict(n_boxes=8, n_kp=MAX_KEYPOINTS), dict(n_boxes=MAX_BOXES, n_kp=300)][c]
        return self.valid(t_ns, **kw)


FEATURE_KINDS = ("malformed", "wrong_type", "unknown_keys", "non_finite", "out_of_image", "oversized_counts",
                 "wrong_descriptor_length", "bad_index", "absurd_times", "edge_valid")


class ObuRoifFuzz(ObuFuzz):
    """The OBU running ``--fusion roif`` under hostile image features (module docstring)."""

    def __init__(self, count: int, seed: int = 0, rate_hz: float = 2000.0, kinds: list[str] | None = None, **kw):
        chosen = list(kinds or [*FEATURE_KINDS, "special"])
        unknown = sorted(set(chosen) - set(FEATURE_KINDS) - {"special"})
        if unknown:
            raise ValueError(f"unknown hostile kind(s) {', '.join(unknown)} for --fusion roif; kinds: "
                             f"{', '.join(FEATURE_KINDS)}, special")
        super().__init__(count, seed=seed, rate_hz=rate_hz, deadline_ms=IMAGE_DEADLINE_MS, **kw)
        self.kinds = chosen
        self.rsu_id = load_scenario(SCENARIO).rsu.id
        self.features = FeatureHostile(self.rng, self.rsu_id)

    def argv(self, duration_s: float) -> dict[str, list[str]]:
        self.eps = {"rsu": free_tcp_endpoint(), "obu": free_tcp_endpoint()}
        base = [sys.executable, "-m", "v2i"]
        common = [*self.common(duration_s), "--scenario", SCENARIO]
        return {"rsu": [*base, "rsu", "--listen", self.eps["rsu"], *common, "--clock-offset-ms", str(CLOCK_OFFSET_MS),
                        "--rsu-id", self.rsu_id, "--source", "camera", "--image-features", "--rate-hz", "10",
                        "--detector-threads", "1"],
                "obu": [*base, "obu", "--listen", self.eps["obu"], "--connect", self.eps["rsu"], *common,
                        "--fusion", "roif", "--roif-threads", "1"]}

    def open(self) -> None:
        super().open()
        s = self.attacker
        self.declare(s.declare_subscriber(keys.obu_image_objects(VEHICLE_ID), self._on_image_objects))
        self.declare(s.declare_subscriber(keys.rsu_image_features(self.rsu_id), self._on_genuine))

    def _on_fused(self, sample) -> None:
        """The object-level output: an OBU fusing images publishes none."""

    def _on_image_objects(self, sample) -> None:
        try:
            out = decode(sample.payload.to_bytes(), ImageFusedBoxes)
        except CodecError:
            return
        self.output(out.t_ns, out.publish_time_ns - out.t_ns > self.deadline_ns, out.view)

    def warmed_up(self) -> bool:
        with self.lock:
            rsus = (self.metrics or {}).get("rsus", [])
        return any(r["rsu_id"] == self.rsu_id and r["clock_offset_ns"] is not None and r["messages_accepted"]
                   for r in rsus)

    def _forge_reply(self, query, rsu_id: str) -> None:
        """No forged clock here: the object-level fuzz covers it."""

    def _rsu_now_ns(self) -> int:
        """A stamp like the genuine RSU's newest frame: its clock (offset) 150 ms ago."""
        return time.time_ns() + round(CLOCK_OFFSET_MS * MS) - 150 * MS

    def _plan(self):
        actions = []
        for kind in [k for k in self.kinds if k in FEATURE_KINDS]:
            make = getattr(self.features, kind)
            if kind == "edge_valid":  # generated when sent: stamped now, so that it pairs
                actions.append((kind, lambda make=make: self._put(self.rsu_id, make(self._rsu_now_ns()))))
                continue
            pool = itertools.cycle([make(self._rsu_now_ns()) for _ in range(POOL)])
            actions.append((kind, lambda pool=pool: self._put(f"x{int(self.rng.integers(8))}", next(pool))))
        actions += self._specials() if "special" in self.kinds else []
        for k in itertools.count():
            if k % len(actions) == 0:
                self.rng.shuffle(actions)
            yield actions[k % len(actions)]

    def _put(self, rsu_id: str, payload: bytes) -> None:
        self.fuzzing = True
        self.attacker.put(keys.rsu_image_features(rsu_id), payload)

    def _specials(self) -> list:
        fake = itertools.count()
        flood = self.features.valid(self._rsu_now_ns(), rsu_id="flood")
        return [("flood", lambda: self._put("flood", flood)),
                ("fake_id", lambda: self._put(f"fake{next(fake) % 200}",
                                              self.features.valid(self._rsu_now_ns(), rsu_id=f"fake{next(fake) % 200}"))),
                ("replay", self._replay)]

    def _replay(self) -> None:
        with self.lock:
            captured = list(self.genuine)
        if captured:
            old = [p for t, p in captured if time.time_ns() - t > REPLAY_AGE_NS]
            self._put(self.rsu_id, old[-1] if old and self.rng.random() < 0.5 else captured[-1][1])

    def expected_outputs(self, seconds: float) -> int:
        return int(seconds * 10)

    def extra(self) -> dict:
        with self.lock:
            m = self.metrics or {}
        return {"fusion": "roif", "cycles": m.get("cycles"), "output_deadline_misses": m.get("output_deadline_misses"),
                "frames_without_rsu": m.get("rsu_deadline_misses")}
