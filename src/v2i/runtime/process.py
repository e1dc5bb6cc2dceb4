"""Process conventions shared by the services and the orchestrator that starts them.

A service prints exactly one JSON line ``{"event": "ready", "service": ...}`` on stdout
once its Zenoh session is open and declared, and stops cleanly on SIGINT or SIGTERM.

The start handshake (``--await-start``): a service loads everything, opens and declares its
session, prints the ready line, then waits for one line on stdin,
``{"event": "start", "start_at_ns": N}`` (``start_line``), N being scenario time zero in Unix ns
(true clock). Only then does it build what depends on time zero (clock model, sources, cycle
schedule), print ``{"event": "started", ..., "ahead_ms": ...}`` (how long before time zero it
began) and run. EOF or SIGINT / SIGTERM before the start line: a clean exit. So an orchestrator
starts the run when every service is ready, whatever the load, instead of guessing a time zero
far enough ahead.
"""

from __future__ import annotations

import gc
import json
import re
import signal
import sys
import threading
import time
from collections.abc import Callable
from typing import TextIO


def stop_on_signals() -> threading.Event:
    """An event set by SIGINT or SIGTERM (main thread only)."""
    stop = threading.Event()

    def _handler(signum, frame):  # noqa: ARG001
        stop.set()

    signal.signal(signal.SIGINT, _handler)
    signal.signal(signal.SIGTERM, _handler)
    return stop


def announce(event: str, service: str, **fields) -> None:
    """One flushed JSON line on stdout for an orchestrator to read."""
    print(json.dumps({"event": event, "service": service, **fields}), flush=True)


def log(service: str, message: str) -> None:
    """A human-readable line on stderr, prefixed with the service name (a node names itself with
    its id: ``obu ego``, ``rsu rsu-nw``); one write, so lines of several threads never interleave."""
    sys.stderr.write(f"[{service}] {message}\n")
    sys.stderr.flush()


START_POLL_S = 0.05  # how often a service waiting for its start line looks at its stop event


def start_line(start_ns: int) -> str:
    """The line an orchestrator writes to a service's stdin to start it at ``start_ns`` (Unix ns)."""
    return json.dumps({"event": "start", "start_at_ns": int(start_ns)}) + "\n"


def parse_start_line(line: str) -> int:
    """``start_at_ns`` of a start line (``start_line``); ValueError saying what is wrong otherwise."""
    try:
        msg = json.loads(line)
    except ValueError:
        raise ValueError(f"not JSON: {line.strip()[:80]!r}") from None
    if not isinstance(msg, dict) or msg.get("event") != "start":
        raise ValueError(f"not a start line: {line.strip()[:80]!r}")
    start_ns = msg.get("start_at_ns")
    if isinstance(start_ns, bool) or not isinstance(start_ns, int) or not 0 < start_ns < 2**63:
        raise ValueError(f"start_at_ns must be a positive 64-bit integer (Unix ns), got {start_ns!r}")
    return start_ns


def read_start_line(service: str, stop: threading.Event, stream: TextIO | None = None) -> int | None:
    """Wait for the start line on ``stream`` (default stdin); its ``start_at_ns``. None when the
    stream ends (EOF) or ``stop`` is set first: the service then exits cleanly. A line that is not
    a start line is logged and skipped."""
    stream = sys.stdin if stream is None else stream
    if stream is None:
        log(service, "--await-start needs a stdin to read the start line from")
        return None
    got: list[int] = []
    done = threading.Event()

    def read() -> None:
        try:
            for line in stream:
                if not line.strip():
                    continue
                try:
                    got.append(parse_start_line(line))
                    return
                except ValueError as exc:
                    log(service, f"ignored a line on stdin ({exc}); waiting for "
                                 '{"event": "start", "start_at_ns": N}')
        except (OSError, ValueError):  # stdin closed under the reader
            pass
        finally:
            done.set()

    threading.Thread(target=read, name="start-line", daemon=True).start()
    while not done.wait(START_POLL_S):
        if stop.is_set():
            return None
    return None if stop.is_set() or not got else got[0]


def start_when_told(service: str, stop: threading.Event, begin: Callable[[int], None], now_ns: Callable[[], int],
                    wait: Callable[[str, threading.Event], int | None] = read_start_line) -> bool:
    """After the ready line (``--await-start``): wait for time zero (``wait``: the start line on stdin,
    or an in-process driver's choice), ``begin(start_ns)``, and announce ``started`` with how many ms
    before time zero it began (negative: late). False when stopped or stdin ended first."""
    start_ns = wait(service, stop)
    if start_ns is None:
        return False
    begin(start_ns)
    announce("started", service, start_at_ns=start_ns,
             ahead_ms=round((start_ns - now_ns()) * 1e-6, 1))
    return True


class ThrottledLog:
    """Logs refusals without flooding: the first of each reason at once, with its detail; after
    that one summary line per ``interval_s`` (the counts since the previous line), so a hostile
    peer cannot fill a disk. The counters in a service's metrics carry the detail."""

    def __init__(self, service: str, interval_s: float = 10.0, clock_s=time.monotonic):
        self.service, self.interval_s, self._clock_s = service, interval_s, clock_s
        self._seen: set[str] = set()
        self._pending: dict[str, int] = {}
        self._totals: dict[str, int] = {}  # the counters as last seen by ``totals``
        self._last_s = clock_s()

    def totals(self, counts: dict[str, int], details: dict[str, str], unit: str = "input(s)") -> None:
        """A service's refusal counters as they stand now: what grew since the last call is
        noted (``details[reason]``, or a count, as the first one's detail), then flushed."""
        for reason, n in counts.items():
            new = n - self._totals.get(reason, 0)
            if new > 0:
                self.refused(reason, details.get(reason, f"{new} {unit}"), new)
        self._totals = dict(counts)
        self.flush()

    def refused(self, reason: str, detail: str, count: int = 1) -> None:
        """Note ``count`` refusals for ``reason``; ``detail`` is logged only for the first one."""
        if reason not in self._seen:
            self._seen.add(reason)
            log(self.service, f"refused ({reason}): {detail}; further refusals are summarised "
                              f"every {self.interval_s:g} s")
            count -= 1
        if count > 0:
            self._pending[reason] = self._pending.get(reason, 0) + count
        self.flush()

    def flush(self, force: bool = False) -> None:
        """The summary line, if one is due (or ``force``) and anything was refused since the last."""
        now_s = self._clock_s()
        if self._pending and (force or now_s - self._last_s >= self.interval_s):
            counts = ", ".join(f"{r} {n}" for r, n in sorted(self._pending.items()))
            log(self.service, f"refused in the last {now_s - self._last_s:.0f} s: {counts}")
            self._pending.clear()
        if force or now_s - self._last_s >= self.interval_s:
            self._last_s = now_s


def add_service_options(p, config_name: str, listen_example: str, seed_of: str) -> None:
    """The options every service shares with ``ServiceConfig`` (flag names = field names)."""
    p.add_argument("--config", metavar="FILE", help=f"YAML file with {config_name} fields (CLI flags override it)")
    p.add_argument("--listen", action="append", metavar="EP",
                   help=f"Zenoh endpoint to listen on, e.g. {listen_example} (repeatable)")
    p.add_argument("--scenario", help="bundled scenario name or YAML path (default red-light-runner)")
    p.add_argument("--seed", type=int, help=f"seed of the {seed_of} (default 0)")
    p.add_argument("--start-at-ns", type=int, help="scenario time zero in Unix ns (true clock); default: now")
    p.add_argument("--await-start", action="store_true", default=None,
                   help='after the ready line, wait for {"event": "start", "start_at_ns": N} on stdin and take N '
                        "as time zero (how v2i demo starts its services when every one is ready); EOF or a signal "
                        "first: a clean exit. Not with --start-at-ns")
    p.add_argument("--duration", dest="duration_s", type=float, help="seconds to run (default: scenario duration)")


# A loop thread that releases the GIL (an ECDSA verify in `cryptography`, ~50 us) waits for it back
# until the thread holding it is forced to switch: 5 ms by default. Next to a busy Python thread a
# 50 us verify took 5.19 ms at 5 ms, 0.64 ms at 0.5 ms (benchmarks/gil_switch.py); in a 20 s demo
# the OBU's verify stage p50 went 0.28 -> 0.15 ms and fuse 1.32 -> 0.92 ms (0.24 -> 0.20, 1.11 -> 1.03
# in a second pair of runs).
SWITCH_INTERVAL_S = 0.0005
M_ARENA_MAX = -8  # glibc malloc.h
SERVICE_MALLOC_ARENAS = 2


def limit_malloc_arenas(arenas: int = SERVICE_MALLOC_ARENAS) -> bool:
    """Cap glibc's malloc arenas (as MALLOC_ARENA_MAX does); False where unsupported.

    Every Zenoh callback thread otherwise gets an arena of its own, and what a burst of large
    messages frees there stays mapped: a fuzzed OBU grew 14-20 MB with the default, 11 MB with 2.
    Call it before any thread starts (a service's first step).
    """
    mallopt = _libc_function("mallopt")
    return mallopt is not None and mallopt(M_ARENA_MAX, arenas) == 1


def freeze_heap() -> None:
    """Move every object alive now (the modules, numba's registries and kernels, the scenario:
    ~150k objects) to the collector's permanent generation (``gc.freeze``), so that a full
    collection later scans only what the process creates from then on. A full collection of that
    start-up heap takes 68-70 ms in a started OBU node (0.0 ms after the freeze): a pause of most
    of a 10 Hz cycle; the first eval run of a short scenario took 0.37-0.40 s with one in it against
    0.29-0.30 s after a freeze. Call it once, when the start-up is done."""
    gc.freeze()


class MemoryTrim:
    """Returns freed heap memory to the system (glibc ``malloc_trim``) at most every ``period_s``.

    What Zenoh callback threads allocate and the service loop frees stays cached in glibc's
    arenas (measured: +8 MB in one arena after a burst of large messages); a service calls
    ``maybe()`` at a quiet moment of its loop. A no-op where glibc is absent.
    """

    def __init__(self, period_s: float = 5.0, clock_s=time.monotonic):
        self.period_s, self._clock_s, self._last_s = period_s, clock_s, clock_s()
        self._trim = _libc_function("malloc_trim")

    def maybe(self) -> bool:
        """Trim if the period has passed; True when it trimmed."""
        now_s = self._clock_s()
        if self._trim is None or now_s - self._last_s < self.period_s:
            return False
        self._last_s = now_s
        self._trim(0)
        return True


def _libc_function(name: str):
    """A function of the C library (glibc on Linux), or None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        import ctypes
        import ctypes.util

        return getattr(ctypes.CDLL(ctypes.util.find_library("c")), name)
    except (OSError, AttributeError):
        return None


def run_service(name: str, model, args, make_node) -> int:
    """``v2i <name>``: config from ``--config`` overridden by every CLI flag named like a
    config field, a node from ``make_node(config)``, run until SIGINT/SIGTERM.

    Returns 2 with the reason on one stderr line when the configuration cannot be used or
    Zenoh refuses its endpoints.
    """
    limit_malloc_arenas()
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    import zenoh

    from v2i.runtime.config import ConfigError, load_config, one_line_error

    overrides = {f: getattr(args, f) for f in model.model_fields if hasattr(args, f)}
    try:
        config = load_config(model, args.config, overrides)
        node = make_node(config)
    except (ConfigError, ValueError, OSError) as exc:
        print(f"v2i {name}: {one_line_error(exc)}", file=sys.stderr)
        return 2
    freeze_heap()
    try:
        node.run(stop_on_signals())
    except zenoh.ZError as exc:
        listen, connect = getattr(config, "listen", []), config.connect
        where = f"listen {', '.join(listen) or '-'}; connect {', '.join(connect) or '-'}"
        print(f"v2i {name}: Zenoh: {zenoh_problem(exc)} ({where})", file=sys.stderr)
        return 2
    return 0


def zenoh_problem(exc: Exception) -> str:
    """The message of a Zenoh error without its Rust source locations and JSON5 wrapping."""
    text = str(exc)
    inner = re.search(r'msg: "(.*?)", location', text)
    return re.sub(r" at \S+\.rs:\d+\.?", "", inner.group(1) if inner else text).strip()
