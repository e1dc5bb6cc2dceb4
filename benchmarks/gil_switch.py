"""What a GIL-releasing call costs the service loop while another Python thread runs, by switch interval.

`cryptography` releases the GIL during an ECDSA verify; the loop then waits for it back until the
thread holding it is forced to switch (``sys.setswitchinterval``, 5 ms by default). Services run
with ``v2i.runtime.process.SWITCH_INTERVAL_S``. Prints verify p50 / p95 (us) idle and next to a busy
thread, at the default interval and at the services' one.

    python benchmarks/gil_switch.py [--n 1000]
"""

from __future__ import annotations

import argparse
import sys
import threading
import time

import numpy as np

from v2i.runtime.process import SWITCH_INTERVAL_S
from v2i.security.envelope import Signer, Verifier
from v2i.security.site import memory_site

KEY = "v2x/rsu/rsu1/objects"


def _verify_us(verifier: Verifier, messages: list[bytes]) -> np.ndarray:
    """(2,) p50, p95 in us of verifying each message once."""
    times = []
    for m in messages:
        t0 = time.perf_counter_ns()
        verifier.verify(m, KEY, None)
        times.append(time.perf_counter_ns() - t0)
    return np.percentile(times, [50, 95]) / 1e3


def _with_busy_thread(fn):
    """``fn()`` while another thread runs pure Python (as a Zenoh callback or a scrape would)."""
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            sum(range(100))

    thread = threading.Thread(target=spin)
    thread.start()
    try:
        return fn()
    finally:
        stop.set()
        thread.join()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=1000, help="messages per row (default %(default)s)")
    n = p.parse_args().n
    t0_ns = time.time_ns()
    trust, ids = memory_site(t0_ns, ["rsu1"])
    signer = Signer(ids["rsu1"])
    verifier = Verifier(trust, "strict")
    messages = iter([signer.sign(b"x" * 200 + k.to_bytes(4, "big"), t0_ns + k, KEY) for k in range(4 * n)])
    rows = []
    for interval_s in (sys.getswitchinterval(), SWITCH_INTERVAL_S):
        sys.setswitchinterval(interval_s)
        batch = lambda: [next(messages) for _ in range(n)]  # noqa: E731 - fresh ones: no replay
        rows.append((f"idle, switch {interval_s * 1e3:g} ms", _verify_us(verifier, batch())))
        rows.append((f"busy thread, switch {interval_s * 1e3:g} ms", _with_busy_thread(lambda: _verify_us(verifier, batch()))))
    print(f"ECDSA P-256 verify of a signed 200 B payload, {n} per row: p50 / p95 us")
    for name, (p50, p95) in rows:
        print(f"  {name:<28} {p50:8.1f} / {p95:8.1f}")


if __name__ == "__main__":
    main()
