"""Cost of signed V2X messages: sign and verify time per message, bytes added; P-256 and Ed25519.

    python benchmarks/signing_cost.py               # 200-object list, 2000 messages per row
    python benchmarks/signing_cost.py --objects 50 --n 5000

The payload is a real RSU object list of ``--objects`` tracks (``benchmarks/wire.py``'s
``rsu_tracks``, encoded by ``schemas.codec``). For each algorithm a fresh site PKI (CA and RSU of
that algorithm) is made in a temporary directory, then, each row timed per call with
``perf_counter_ns`` over ``--n`` messages (p50 and p95, microseconds):

- ``sign``: ``Signer.sign`` (digest signer field; the certificate interval set beyond the run);
- ``verify cached``: ``Verifier.verify`` of distinct genuine messages whose certificate is in the
  verifier's cache (the steady state: signature + freshness + replay window);
- ``verify uncached``: a new ``Verifier`` per message, the message carrying its full certificate
  (CA check of the certificate + message signature: the first message from a new RSU);
- ``signature only``: ``algorithms.verify`` alone (what the envelope adds on top of the crypto);
- ``reject forged``: a message with one payload byte changed (``bad_signature``: a full verify);
- ``reject unknown``: a digest no certificate matches (``unknown_cert``: no crypto at all).

Bytes added: with the digest signer field, with the full certificate, and the mean over 10 s at
10 Hz of a default ``Signer`` (full certificate once per second).

Targets (issue 14): verify <= 200 us per list, <= 120 B added per message.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import msgpack
import numpy as np

from v2i.fusion.wire import states_from_objects
from schemas.codec import encode
from schemas.messages import ObjectList
from v2i.security import algorithms as alg
from v2i.security.envelope import Signer, Verifier, signed_bytes
from v2i.security.pki import Pki, load_signer, load_trust
from wire import HEADER, rsu_tracks  # benchmarks/wire.py: the same list as the wire benchmark

T0 = 1_700_000_000 * 10**9
KEY = "v2x/rsu/rsu-0/objects"
TARGET_VERIFY_US = 200.0
TARGET_ADDED_B = 120


def timed_us(calls: list[Callable[[], object]]) -> tuple[float, float]:
    """(p50, p95) in microseconds of each call timed alone."""
    samples = []
    for call in calls:
        t = time.perf_counter_ns()
        call()
        samples.append((time.perf_counter_ns() - t) / 1e3)
    q = statistics.quantiles(samples, n=20)
    return statistics.median(samples), q[18]


def site(directory: Path, algorithm: str) -> tuple[Signer, object]:
    Pki.init(directory, T0, algorithm=algorithm).issue("rsu-0", "rsu", T0, algorithm=algorithm)
    return Signer(load_signer(directory, "rsu-0"), cert_interval_ns=1 << 62), load_trust(directory)


def measure(algorithm: str, payload: bytes, n: int) -> dict[str, object]:
    with tempfile.TemporaryDirectory() as tmp:
        signer, trust = site(Path(tmp), algorithm)
    times = [T0 + 1 + i * 100_000_000 for i in range(n)]
    first = signer.sign(payload, T0, KEY)  # carries the certificate
    row: dict[str, object] = {"sign": timed_us([lambda t=t: signer.sign(payload, t, KEY) for t in times])}
    envs = [signer.sign(payload, t, KEY) for t in times]
    v = Verifier(trust, "strict", freshness_ns=1 << 62)
    assert v.verify(first, KEY, T0)[1] == "ok"
    row["verify cached"] = timed_us([lambda e=e, t=t: v.verify(e, KEY, t) for e, t in zip(envs, times)])
    assert v.counts["ok"] == n + 1, v.counts
    signer.request_certificate()
    full = signer.sign(payload, T0, KEY)
    fresh = [Verifier(trust, "strict") for _ in range(n)]
    row["verify uncached"] = timed_us([lambda f=f: f.verify(full, KEY, T0) for f in fresh])
    assert all(f.counts["ok"] == 1 for f in fresh)
    tbs = signed_bytes(payload, signer.digest, times[0], KEY)
    sig = msgpack.unpackb(envs[0])[4]
    public = signer.identity.key.public_key()
    row["signature only"] = timed_us([lambda: alg.verify(public, sig, tbs)] * n)
    items = msgpack.unpackb(envs[0])
    items[1] = payload[:-1] + bytes([payload[-1] ^ 1])
    forged = msgpack.packb(items)
    row["reject forged"] = timed_us([lambda: v.verify(forged, KEY, times[0])] * n)
    items[1], items[2] = payload, b"\x00" * 8
    unknown = msgpack.packb(items)
    row["reject unknown"] = timed_us([lambda: v.verify(unknown, KEY, times[0])] * n)
    assert v.counts["bad_signature"] == n and v.counts["unknown_cert"] == n, v.counts
    row["added"] = (len(envs[0]) - len(payload), len(full) - len(payload), mean_added_b(signer, payload))
    return row


def mean_added_b(signer: Signer, payload: bytes, rate_hz: int = 10, seconds: int = 10) -> float:
    """Mean bytes added per message by a default Signer (full certificate once per second) at
    ``rate_hz`` over ``seconds``."""
    default = Signer(signer.identity)
    step_ns = 10**9 // rate_hz
    sizes = [len(default.sign(payload, T0 + i * step_ns, KEY)) - len(payload) for i in range(rate_hz * seconds)]
    return sum(sizes) / len(sizes)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", type=int, default=200, help="objects in the list (default 200)")
    ap.add_argument("--n", type=int, default=2000, help="messages per timed row (default 2000)")
    args = ap.parse_args(argv)
    objs = rsu_tracks(args.objects, np.random.default_rng(14))
    payload = encode(ObjectList(header=HEADER, objects=states_from_objects(objs)))
    print(f"payload: {args.objects}-object ObjectList, {len(payload)} B; {args.n} messages per row; "
          f"times p50 / p95 in us per message")
    rows = {a: measure(a, payload, args.n) for a in (alg.P256, alg.ED25519)}
    names = [k for k in rows[alg.P256] if k != "added"]
    print(f"{'':18s}" + "".join(f"{a:>20s}" for a in rows))
    for name in names:
        print(f"{name:18s}" + "".join(f"{r[name][0]:>11.1f} / {r[name][1]:<6.1f}" for r in rows.values()))
    print(f"{'bytes added':18s}" + "".join(f"{r['added'][0]:>11d} B {'':6s}" for r in rows.values()))
    print(f"{'  with full cert':18s}" + "".join(f"{r['added'][1]:>11d} B {'':6s}" for r in rows.values()))
    print(f"{'  mean at 10 Hz':18s}" + "".join(f"{r['added'][2]:>11.1f} B {'':6s}" for r in rows.values()))
    for a, r in rows.items():
        ok_v = r["verify cached"][0] <= TARGET_VERIFY_US
        ok_b = r["added"][0] <= TARGET_ADDED_B
        print(f"{a}: verify cached p50 {r['verify cached'][0]:.1f} us "
              f"({'meets' if ok_v else 'MISSES'} <= {TARGET_VERIFY_US:.0f} us), "
              f"{r['added'][0]} B added ({'meets' if ok_b else 'MISSES'} <= {TARGET_ADDED_B} B; "
              f"{r['added'][1]} B in the messages that carry the certificate)")


if __name__ == "__main__":
    main()
