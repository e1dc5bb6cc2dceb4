"""What an attacker near an RSU sends against a signed V2X site, per kind (pure, seeded).

The attacker holds no site key of its own. It can hold, in the acceptance scenario:
- a *stolen* key of another RSU (``rsu-evil``: certificate for ``v2x/rsu/rsu-evil/**``) and of a
  vehicle (``stolen-vehicle``: ``v2x/obu/stolen-vehicle/**``): genuine site certificates that
  simply do not cover the victim RSU's keys;
- a *revoked* key: a former certificate of the victim RSU itself (``{rsu_id}-revoked``, covering
  ``v2x/rsu/{rsu_id}/**``), on the CA's revocation list. Without that list it would pass: the
  revocation is the only thing that stops it;
- genuine envelopes it captured over the air (the RSU's broadcast), and the genuine RSU's
  certificate digest they carry.
The keys are the lab's to give (``v2i.security.attacker_keys``, made by ``v2i pki attacker DIR``).

Kinds (``KINDS``) and the :class:`v2i.security.envelope.Verifier` reason each is built to hit
(``INTENDED``), all on the victim RSU's own keys:

- ``unsigned``: a plain v2i ObjectList with one ghost pedestrian ``GHOST_AHEAD_M`` ahead of the
  ego (map frame) -> ``unsigned``;
- ``forged``: the same list in an envelope naming the genuine RSU's digest, signed with a random
  64-byte string or with the attacker's own fresh key -> ``bad_signature``;
- ``replayed``: a captured genuine envelope, byte for byte -> ``replayed`` (``stale`` once older
  than the verifier's freshness window);
- ``wrong_key``: the ghost list signed with a stolen key (rsu-evil or the vehicle), its whole
  certificate in the envelope (key substitution) -> ``wrong_key`` (``wrong_role`` for the vehicle's
  where the verifier takes RSU certificates only, as the OBU does);
- ``revoked``: the ghost list signed with the revoked former key of the RSU -> ``revoked``;
- ``time``: answers to the OBU's time queries claiming the RSU's clock is ``shift_ns`` further
  ahead: unsigned, wrong-key and forged-digest variants -> ``unsigned`` / ``wrong_key`` (or
  ``wrong_role``) / ``bad_signature``;
- ``control``: a LinkControl outage of the whole link for an hour, unsigned and signed by a
  non-operator (stolen) key -> ``unsigned`` / ``wrong_role`` at the link emulator.

Opt-in kinds against the genuine RSU's share of the OBU (``HOSTILE_KINDS``, issue 32; not in the
default list, each runs for seconds rather than a count):

- ``flood``: at a high rate on the genuine RSU's own ``v2x/rsu/{rsu_id}/objects``, junk (random
  bytes, half of them behind the envelope prefix), unsigned ghost lists and forged envelopes
  naming the genuine digest with a random signature and a fresh generation time
  (``FLOOD_VARIANTS``) -> ``unsigned`` / ``malformed`` / ``bad_signature``; what it costs is
  the genuine RSU's lists the OBU no longer takes;
- ``time_doubled`` / ``time_delayed``: no bytes of the attacker's own: the OBU's time queries are
  relayed to the genuine RSU and its signed replies returned twice, or the request leg delayed
  (``v2i.adversary.attack_relay``).

Generation times are the RSU's clock as the attacker estimates it from captured envelopes
(``generation_ns`` minus local receive time), so forged messages are fresh and cost the verifier
a signature check. Nothing here reads a clock or touches Zenoh; randomness from the injected rng.
"""

from __future__ import annotations

import itertools

import msgpack
import numpy as np

from v2i.core.frames import Pose2D
from schemas import keys
from schemas.classes import ObjectClass
from schemas.codec import encode
from schemas.messages import LinkControl, ObjectList, ObjectListHeader, ObjectState, TimeReply, TimeRequest
from v2i.security import algorithms as alg
from v2i.security import certificates as certs
from v2i.security.attacker_keys import AttackerKeys
from v2i.security.envelope import MAGIC, PREFIX, Signer, parse, signed_bytes

KINDS = ("unsigned", "forged", "replayed", "wrong_key", "revoked", "time", "control")
LIST_KINDS = KINDS[:5]  # object lists on v2x/rsu/{rsu_id}/objects
HOSTILE_KINDS = ("flood", "time_doubled", "time_delayed")  # opt-in, timed: against the genuine RSU's share
ALL_KINDS = KINDS + HOSTILE_KINDS
RELAY_KINDS = HOSTILE_KINDS[1:]  # genuine time replies relayed
FLOOD_VARIANTS = ("junk", "unsigned", "forged")
JUNK_BYTES = (8, 512)  # a junk message's length, drawn uniformly in [lo, hi)
# the stolen RSU key fails on coverage (wrong_key); the stolen vehicle key already on its role where
# the verifier takes RSU certificates only (the OBU), and both where only operators may (link control)
INTENDED: dict[str, tuple[str, ...]] = {
    "unsigned": ("unsigned",), "forged": ("bad_signature",), "replayed": ("replayed", "stale"),
    "wrong_key": ("wrong_key", "wrong_role"), "revoked": ("revoked",),
    "time": ("unsigned", "wrong_key", "wrong_role", "bad_signature"), "control": ("unsigned", "wrong_role", "wrong_key"),
    "flood": ("unsigned", "malformed", "bad_signature"),
}
TIME_VARIANTS = ("unsigned", "wrong_key", "forged")
CONTROL_VARIANTS = ("unsigned", "wrong_key")
GHOST_AHEAD_M = 8.0
GHOST_ID = 0xB0_0000  # the ghost's object id on the attacker's lists
GHOST_SIZE_LWH_M = (0.6, 0.6, 1.75)  # a pedestrian
TIME_SHIFT_NS = 400_000_000  # forged time replies move the RSU clock estimate by this much
RSU_LATENCY_NS = 100_000_000  # a ghost list claims capture this long before its publication
OUTAGE_S = 3600.0


def signer_digest(envelope: bytes) -> bytes | None:
    """The signer's certificate digest named by a captured envelope, None if it is not one."""
    envelope = bytes(envelope)
    parsed = parse(envelope) if envelope.startswith(PREFIX) else None
    if parsed is None:
        return None
    return parsed.signer if len(parsed.signer) == certs.DIGEST_BYTES else certs.digest(parsed.signer)


def ghost_xy(ego: Pose2D, ahead_m: float = GHOST_AHEAD_M) -> np.ndarray:
    """Map position (2,) ``ahead_m`` along the ego's heading: p = t + d (cos yaw, sin yaw)."""
    return np.array([ego.x + ahead_m * np.cos(ego.yaw), ego.y + ahead_m * np.sin(ego.yaw)])


def ghost_list(rsu_id: str, seq: int, capture_ns: int, publish_ns: int, xy: np.ndarray) -> bytes:
    """An encoded v2i ObjectList of ``rsu_id`` holding one standing ghost pedestrian at map ``xy``."""
    length, width, height = GHOST_SIZE_LWH_M
    ghost = ObjectState(id=GHOST_ID, cls=ObjectClass.PEDESTRIAN, x=float(xy[0]), y=float(xy[1]), length=length,
                        width=width, height=height, cov_xx=0.04, cov_yy=0.04, confidence=0.95)
    header = ObjectListHeader(rsu_id=rsu_id, seq=seq, capture_time_ns=capture_ns, publish_time_ns=publish_ns,
                              sensor="camera")
    return encode(ObjectList(header=header, objects=[ghost]))


def _envelope(payload: bytes, signer: bytes, generation_ns: int, signature: bytes) -> bytes:
    return msgpack.packb([MAGIC, payload, signer, generation_ns, signature])


class AttackMessages:
    """Builds the bytes of each kind for victim RSU ``rsu_id``.

    ``genuine_digest``: the victim's certificate digest (from a captured envelope:
    :func:`signer_digest`); needed by ``forged`` and the forged time replies.
    """

    def __init__(self, rsu_id: str, attacker: AttackerKeys, rng: np.random.Generator,
                 genuine_digest: bytes | None = None, link_id: str = "link1", shift_ns: int = TIME_SHIFT_NS):
        self.rsu_id, self.link_id, self.rng = keys.check_id(rsu_id), keys.check_id(link_id), rng
        self.genuine_digest, self.shift_ns = genuine_digest, shift_ns
        # cert_interval_ns=0: every message carries the whole certificate, so a verifier that never
        # saw it resolves it and judges the key coverage, not the unknown digest
        self._stolen = itertools.cycle([Signer(identity, cert_interval_ns=0) for identity in attacker.stolen])
        self._revoked = Signer(attacker.revoked, cert_interval_ns=0)
        self._own_key = alg.generate(alg.P256)  # the attacker's own key: no certificate names it
        self._seq = itertools.count(int(rng.integers(1 << 40)))

    # --- object lists -----------------------------------------------------------------------------
    def ghost_payload(self, rsu_now_ns: int, ego: Pose2D) -> bytes:
        """A ghost list stamped as the RSU would at ``rsu_now_ns`` (RSU clock), ego pose at capture."""
        return ghost_list(self.rsu_id, next(self._seq), rsu_now_ns - RSU_LATENCY_NS, rsu_now_ns, ghost_xy(ego))

    def list_message(self, kind: str, rsu_now_ns: int, ego: Pose2D, captured: bytes | None = None) -> tuple[str, bytes]:
        """(key expression, bytes) of one object-list attack of ``kind`` (``LIST_KINDS``);
        ``captured``: a genuine envelope (``replayed`` only)."""
        key_expr = keys.rsu_objects(self.rsu_id)
        if kind == "replayed":
            if captured is None:
                raise ValueError("a replay needs a captured genuine envelope")
            return key_expr, bytes(captured)
        payload = self.ghost_payload(rsu_now_ns, ego)
        if kind == "unsigned":
            return key_expr, payload
        if kind == "forged":
            return key_expr, self.forged(payload, rsu_now_ns, key_expr)
        if kind == "wrong_key":
            return key_expr, next(self._stolen).sign(payload, rsu_now_ns, key_expr)
        if kind == "revoked":
            return key_expr, self._revoked.sign(payload, rsu_now_ns, key_expr)
        raise ValueError(f"unknown list attack {kind!r}: one of {', '.join(LIST_KINDS)}")

    def forged(self, payload: bytes, generation_ns: int, key_expr: str) -> bytes:
        """An envelope naming the genuine RSU's digest with a random signature or one by the
        attacker's own key over the right bytes (half each)."""
        if self.genuine_digest is None:
            raise ValueError("forging needs the genuine RSU's certificate digest (capture one of its messages)")
        digest = self.genuine_digest
        if self.rng.random() < 0.5:
            signature = self.rng.bytes(alg.SIGNATURE_BYTES)
        else:
            signature = alg.sign(self._own_key, signed_bytes(payload, digest, generation_ns, key_expr))
        return _envelope(payload, digest, generation_ns, signature)

    def flood(self, variant: str, rsu_now_ns: int, ego: Pose2D, payload: bytes | None = None) -> bytes:
        """One flood message of ``variant`` (``FLOOD_VARIANTS``) for the victim's objects key, stamped
        at ``rsu_now_ns`` (RSU clock): junk, an unsigned ghost list, or a ghost list in an envelope
        naming the genuine digest with a random signature (no signing cost to the attacker; the
        same verify cost to the OBU as any bad signature). ``payload``: a ghost list made by
        :meth:`ghost_payload` to reuse (encoding one costs ~150 us; at 2000/s the sender reuses
        one per batch), default a new one."""
        if variant == "junk":
            junk = self.rng.bytes(int(self.rng.integers(*JUNK_BYTES)))
            # half behind the envelope prefix: the verifier parses it before refusing it as malformed
            return PREFIX + junk if self.rng.random() < 0.5 else junk
        payload = self.ghost_payload(rsu_now_ns, ego) if payload is None else payload
        if variant == "unsigned":
            return payload
        if variant == "forged":
            if self.genuine_digest is None:
                raise ValueError("forging needs the genuine RSU's certificate digest (capture one of its messages)")
            return _envelope(payload, self.genuine_digest, rsu_now_ns, self.rng.bytes(alg.SIGNATURE_BYTES))
        raise ValueError(f"unknown flood variant {variant!r}: one of {', '.join(FLOOD_VARIANTS)}")

    # --- time replies -----------------------------------------------------------------------------
    def time_reply(self, request: TimeRequest, rsu_offset_ns: int, variant: str) -> bytes:
        """A reply to ``request`` claiming the RSU clock is ``rsu_offset_ns + shift_ns`` ahead of
        the OBU's, with a precise-looking 50 us turnaround: t2 = t1 + offset + shift + 0.5 ms."""
        t2_ns = request.t1_ns + rsu_offset_ns + self.shift_ns + 500_000
        payload = encode(TimeReply(rsu_id=self.rsu_id, seq=request.seq, t1_ns=request.t1_ns, t2_ns=t2_ns,
                                   t3_ns=t2_ns + 50_000))
        key_expr = keys.rsu_time(self.rsu_id)
        if variant == "unsigned":
            return payload
        if variant == "wrong_key":
            return next(self._stolen).sign(payload, t2_ns, key_expr)
        if variant == "forged":
            return self.forged(payload, t2_ns, key_expr)
        raise ValueError(f"unknown time reply variant {variant!r}: one of {', '.join(TIME_VARIANTS)}")

    # --- link control -----------------------------------------------------------------------------
    def control(self, variant: str, seq: int, generation_ns: int) -> tuple[str, bytes]:
        """(key, bytes) of a LinkControl cutting the whole link for an hour: unsigned, or signed
        by a stolen non-operator key (its certificate does not cover ``v2x/link/*/control``)."""
        key_expr = keys.link_control(self.link_id)
        payload = encode(LinkControl(link_id=self.link_id, seq=seq, outage=True, duration_s=OUTAGE_S))
        if variant == "unsigned":
            return key_expr, payload
        if variant == "wrong_key":
            return key_expr, next(self._stolen).sign(payload, generation_ns, key_expr)
        raise ValueError(f"unknown control variant {variant!r}: one of {', '.join(CONTROL_VARIANTS)}")
