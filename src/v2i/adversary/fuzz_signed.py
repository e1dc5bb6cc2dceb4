"""``v2i fuzz --target obu-signed``: hostile *signed envelopes* against an OBU with ``--security strict``.

The topology of ``obu`` (``v2i.adversary.fuzz_targets.ObuFuzz``: an RSU, 250 ms clock offset, and the
OBU connected to it), both with a site PKI made in a temporary directory: the RSU signs, the OBU
verifies strictly. The site also has eight fuzzing RSUs ``x0`` .. ``x7`` whose keys the fuzzer
holds, so that it can put a *valid* signature over anything. Kinds (``SIGNED_KINDS``), on the
keys ``v2x/rsu/x{i}/objects`` (``predictions`` for prediction lists):

- ``garbage_prefix``: random bytes before a valid envelope (-> ``unsigned``), or random bytes
  after the envelope prefix (-> ``malformed``);
- ``truncated``: a valid envelope cut anywhere (-> ``malformed``, or ``unsigned`` under 4 bytes);
- ``huge_fields``: the envelope's fields out of every bound: a payload over 1 MiB, a 4 KiB signer,
  a 64 KiB signature, generation times of 2^64 and -1, six fields, a map for the payload, a
  signer field that decodes as a certificate of garbage (-> ``malformed`` / ``unknown_cert``);
- ``bit_flips``: 1-8 bits flipped in a valid envelope (-> ``bad_signature``, ``malformed``, ...);
- ``signed_hostile``: every ``v2i.adversary.hostile`` payload (random bytes, wrong shapes,
  non-finite values, ...) validly signed by ``x{i}``: the verifier passes it and the decoder
  behind it must refuse it (``codec_*``, ``too_large``, ...), never crash;
- ``special``: the genuine RSU's lists replayed on its own key (-> ``replayed``).

What the OBU refused is its own ``rejected`` counters (``security_<reason>`` and the decoder's).
"""

from __future__ import annotations

import itertools
import tempfile
import time
from pathlib import Path

import msgpack
import numpy as np

from schemas import keys
from v2i.security.envelope import PREFIX, Signer
from v2i.security.pki import load_signer
from v2i.security.site import write_site

from v2i.adversary.fuzz import POOL_PER_KIND
from v2i.adversary.fuzz_targets import CLOCK_OFFSET_MS, ObuFuzz
from v2i.adversary.hostile import KINDS as HOSTILE_KINDS

SIGNED_KINDS = ("garbage_prefix", "truncated", "huge_fields", "bit_flips", "signed_hostile")
FUZZ_RSUS = tuple(f"x{i}" for i in range(8))


class SignedHostile:
    """Hostile envelopes around the payloads of ``hostile`` (a ``HostileInputs``), signed by
    ``signers`` (rsu id -> Signer) where a kind needs a valid signature."""

    def __init__(self, rng: np.random.Generator, hostile, signers: dict[str, Signer]):
        self.rng, self.hostile, self.signers = rng, hostile, signers
        self._tick = itertools.count()

    def make(self, kind: str, type_name: str, rsu_id: str, generation_ns: int) -> bytes:
        key_expr = (keys.rsu_objects if type_name == "object_list" else keys.rsu_predictions)(rsu_id)
        unique_ns = generation_ns + next(self._tick)  # each envelope new to the replay window
        if kind == "signed_hostile":
            payload = self.hostile.make(str(self.rng.choice(list(HOSTILE_KINDS))), type_name, generation_ns)
            return self.signers[rsu_id].sign(payload, unique_ns, key_expr)
        valid = self.signers[rsu_id].sign(self.hostile.valid(type_name, generation_ns), unique_ns, key_expr)
        return getattr(self, kind)(valid)

    def garbage_prefix(self, valid: bytes) -> bytes:
        junk = self.rng.bytes(int(self.rng.integers(1, 64)))
        return junk + valid if self.rng.random() < 0.5 else PREFIX + junk + valid[len(PREFIX):]

    def truncated(self, valid: bytes) -> bytes:
        return valid[: int(self.rng.integers(0, len(valid)))]

    def bit_flips(self, valid: bytes) -> bytes:
        data = bytearray(valid)
        for i in self.rng.integers(0, len(data), int(self.rng.integers(1, 9))):
            data[i] ^= 1 << int(self.rng.integers(8))
        return bytes(data)

    def huge_fields(self, valid: bytes) -> bytes:
        fields = list(msgpack.unpackb(valid))  # [MAGIC, payload, signer, generation_ns, signature]
        choice = int(self.rng.integers(7))
        if choice == 0:
            fields[1] = self.rng.bytes((1 << 20) + int(self.rng.integers(1, 4096)))  # over MAX_ENVELOPE_BYTES
        elif choice == 1:
            fields[2] = self.rng.bytes(int(self.rng.integers(1025, 4096)))  # over MAX_CERT_BYTES
        elif choice == 2:
            fields[4] = self.rng.bytes(1 << 16)
        elif choice == 3:
            fields[3] = [-1, -(2**63), 2**64 - 1][int(self.rng.integers(3))]
        elif choice == 4:
            fields.append(self.rng.bytes(16))  # six fields: no longer the envelope prefix
        elif choice == 5:
            fields[1] = {"d": fields[1]}
        else:
            fields[2] = self.rng.bytes(int(self.rng.integers(9, 300)))  # "a certificate" of garbage
        return msgpack.packb(fields)


class ObuSignedFuzz(ObuFuzz):
    """``ObuFuzz`` with a site PKI: the RSU signs, the OBU verifies with ``--security strict``."""

    name = "obu-signed"

    def __init__(self, count: int, kinds: list[str] | None = None, **kw):
        unknown = sorted(set(kinds or ()) - set(SIGNED_KINDS) - {"special"})
        if unknown:
            raise ValueError(f"unknown signed hostile kind(s) {', '.join(unknown)}; kinds: "
                             f"{', '.join(SIGNED_KINDS)}, special")
        super().__init__(count, **kw)
        self.kinds = list(kinds or [*SIGNED_KINDS, "special"])
        self._tmp = tempfile.TemporaryDirectory(prefix="v2i-fuzz-pki-")
        self.pki = Path(self._tmp.name)
        write_site(self.pki, time.time_ns() - 3600 * 10**9, rsu_ids=["rsu1", *FUZZ_RSUS], vehicle_ids=["ego"])
        self.signed = SignedHostile(self.rng, self.hostile,
                                    {r: Signer(load_signer(self.pki, r)) for r in FUZZ_RSUS})

    def argv(self, duration_s: float) -> dict[str, list[str]]:
        argv = super().argv(duration_s)
        argv["rsu"] += ["--pki", str(self.pki)]
        # the victim's process is looked up by the target's name
        return {"rsu": argv["rsu"], self.name: [*argv["obu"], "--pki", str(self.pki), "--security", "strict"]}

    def run(self) -> dict:
        try:
            return super().run()
        finally:
            self._tmp.cleanup()

    def _deliver_keyed(self, typ: str, key_and_payload: tuple[str, bytes]) -> None:
        key, payload = key_and_payload
        self.deliver(typ, payload, key)

    def _plan(self):
        """(kind, send) over the signed kinds and both list types, shuffled each round."""
        now_rsu_ns = time.time_ns() + round(CLOCK_OFFSET_MS * 1e6)
        actions = []
        for kind, typ in itertools.product([k for k in self.kinds if k in SIGNED_KINDS], self.input_types):
            pool = []
            for _ in range(POOL_PER_KIND):
                rsu_id = str(self.rng.choice(FUZZ_RSUS))
                key = (keys.rsu_objects if typ == "object_list" else keys.rsu_predictions)(rsu_id)
                pool.append((key, self.signed.make(kind, typ, rsu_id, now_rsu_ns)))
            cycle = itertools.cycle(pool)
            actions.append((f"{kind}:{typ}", lambda typ=typ, cycle=cycle: self._deliver_keyed(typ, next(cycle))))
        if "special" in self.kinds:  # the genuine RSU's own lists again: replayed
            actions.append(("replay", self._replay))
        for k in itertools.count():
            if k % len(actions) == 0:
                self.rng.shuffle(actions)
            yield actions[k % len(actions)]
