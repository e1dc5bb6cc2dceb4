"""``v2i fuzz``: hostile traffic against one live service, and what it did to the service.

The target runs as its own process, as in ``v2i demo`` (``v2i.adversary.fuzz_targets``: ``obu``
with an RSU connected directly, ``rsu`` alone, ``link`` between the fuzzer's own RSU and
vehicle sessions). The fuzzer's Zenoh sessions sit where an attacker would. The services start
with the start handshake (``v2i.orchestration.children``): once every one is ready (one bound,
``ready_timeout_s``), the fuzzer subscribes and sends time zero. It waits until the target's
normal output flows, then sends ``count`` hostile messages at ``rate_hz``: every
kind of ``v2i.adversary.hostile`` on every input the target has, plus floods (one payload again
and again on one key), fake ids, replays of captured genuine lists and forged time replies
(per target). It watches the normal output meanwhile and reports: messages sent by kind,
refusals by reason (the target's own counters), crashes (the process exited), outputs late
or missing in the fuzzing window, and the target's RSS before and after.

Kind ``trickle`` (alone; ``v2i.adversary.trickle``) sends no message: ``trickle_connections`` raw
TCP sockets (default 300) to the target's listen endpoint, one byte each per tick, reopened when
the listener closed them. ``count`` and ``rate_hz`` keep their meaning with each byte a hostile
message: the trickle lasts ``count / rate_hz`` seconds and each socket sends a byte every
``trickle_connections / rate_hz`` seconds (``--kinds trickle --count 3000 --rate 150``: 300 sockets,
a byte every 2 s each, 20 s). The report adds what the trickle did (opens, reopens, refused
connects, bytes) and, for the OBU, the genuine RSU lists published and accepted meanwhile.
"""

from __future__ import annotations

import itertools
import sys
import threading
import time
from abc import ABC, abstractmethod
from collections import Counter
from pathlib import Path

import numpy as np

from v2i.core.jit import load_kernels
from v2i.offline.kernels import RUN_KERNEL_MODULES
from v2i.runtime.transport import open_session

from v2i.orchestration.children import READY_TIMEOUT_S, Child, DemoError, start_all, wait_ready
from v2i.adversary.hostile import KINDS, HostileInputs
from v2i.adversary.trickle import TrickleSpec, parse_endpoint, run_trickle

RSU_ID, VEHICLE_ID, LINK_ID = "rsu1", "ego", "link1"
POOL_PER_KIND = 40  # distinct payloads per (kind, message type), sent round-robin
MS = 1_000_000
# from time zero until the target works normally (``FuzzRun.warmed_up``): its first 5 outputs (0.5 s at
# 10 Hz, 1 s at the RSU's 5 Hz) and the OBU's first clock estimate and accepted RSU list (its sync
# starts 1 s before time zero); generous for a loaded machine, where a cycle can take several times longer
WARM_UP_S = 30.0
FLOWING_OUTPUTS = 5  # normal outputs seen before the fuzzing starts
TRICKLE = "trickle"  # the kind that sends no message: raw TCP sockets trickling bytes (v2i.adversary.trickle)
TRICKLE_CONNECTIONS = 300  # sockets of a trickle: 3 times Zenoh's default pending handshakes (100)


def rss_mb(pid: int) -> float | None:
    """Resident set size of a process (MB), None once it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


class Crashed(RuntimeError):
    """A service process exited while it was being fuzzed."""

    def __init__(self, name: str, code: int):
        super().__init__(f"{name} exited with code {code}")
        self.name, self.code = name, code


class FuzzRun(ABC):
    """The common driver; a target subclass (``fuzz_targets``) says what to start, where its
    inputs are (``deliver``), what its normal output is (``outputs``) and what it refused."""

    name = "?"
    input_types: tuple[str, ...] = ()
    trickle_target: str | None = None  # the ``eps`` entry a trickle goes to (the target's listen endpoint)

    def __init__(self, count: int, seed: int = 0, rate_hz: float = 2000.0, ready_timeout_s: float = READY_TIMEOUT_S,
                 settle_s: float = 3.0, deadline_ms: float = 100.0, kinds: list[str] | None = None,
                 progress=sys.stderr, trickle_connections: int = TRICKLE_CONNECTIONS):
        """``ready_timeout_s``: every service must say it is ready within this (``--ready-timeout``);
        ``progress``: where the progress lines go (None: nowhere); ``trickle_connections``: the
        sockets of kind ``trickle``."""
        if count < 1 or not rate_hz > 0:
            raise ValueError("--count must be >= 1 and --rate > 0")
        unknown = sorted(set(kinds or ()) - set(KINDS) - {"special", TRICKLE})
        if unknown:
            raise ValueError(f"unknown hostile kind(s) {', '.join(unknown)}; kinds: {', '.join(KINDS)}, special, "
                             f"{TRICKLE}")
        self.kinds = list(kinds or [*KINDS, "special"])
        self.trickle = self._trickle_spec(count, rate_hz, trickle_connections) if TRICKLE in self.kinds else None
        self.trickled: dict | None = None  # what the trickle did (TrickleCounts.as_dict)
        if not ready_timeout_s > 0:
            raise ValueError("--ready-timeout must be > 0")
        self.count, self.rate_hz, self.ready_timeout_s, self.settle_s = count, rate_hz, ready_timeout_s, settle_s
        self.deadline_ns = round(deadline_ms * MS)
        self.rng = np.random.default_rng(seed)
        self.hostile = HostileInputs(self.rng, RSU_ID, VEHICLE_ID, LINK_ID)
        self.sent: Counter[str] = Counter()
        self.lock = threading.Lock()  # the callbacks' state below
        self.outputs: list[tuple[int, bool, str | None]] = []  # (time of the normal output, late, its mode)
        self.children: dict[str, Child] = {}
        self.progress = progress
        self.ready_s: float | None = None  # every service ready this long after they were started
        self.warm_up_s: float | None = None  # the target working normally this long after time zero
        self.eps: dict[str, str] = {}
        self.stop = threading.Event()  # set when the run ends: the fuzzer's own threads end
        self._sessions: list = []
        self._declared: list = []
        self._refused_at_start: Counter[str] = Counter()

    def _trickle_spec(self, count: int, rate_hz: float, connections: int) -> TrickleSpec:
        """``connections`` sockets, ``count`` bytes at ``rate_hz`` in all: a byte every
        connections / rate_hz seconds each, for count / rate_hz seconds."""
        if self.kinds != [TRICKLE]:
            raise ValueError(f"kind {TRICKLE} runs alone (--kinds {TRICKLE})")
        if self.trickle_target is None:
            raise ValueError(f"fuzz target {self.name}: no listen endpoint to trickle")
        return TrickleSpec(connections=connections, byte_interval_s=connections / rate_hz, duration_s=count / rate_hz)

    # --- what a target provides ---------------------------------------------------------------
    @abstractmethod
    def argv(self, duration_s: float) -> dict[str, list[str]]:
        """Service name -> command line of each process to start (``common`` flags on each service's:
        it waits for its start line); ``self.name`` is the target."""

    @staticmethod
    def common(duration_s: float) -> list[str]:
        """The flags of every service the fuzzer starts (not the link emulator's): time zero from the
        start line, run ``duration_s`` from it."""
        return ["--await-start", "--duration", str(duration_s)]

    @abstractmethod
    def open(self) -> None:
        """Open the fuzzer's sessions and declare what watches the target."""

    @abstractmethod
    def deliver(self, typ: str, payload: bytes) -> None:
        """Send one payload of message type ``typ`` to one of the target's inputs."""

    @abstractmethod
    def refused(self) -> Counter[str]:
        """The target's own refusal counters (cumulative), by reason."""

    @abstractmethod
    def expected_outputs(self, seconds: float) -> int:
        """Normal outputs the target should produce in ``seconds``."""

    def special_actions(self) -> list[tuple[str, object]]:
        """(kind, send) beyond the pool kinds: floods, fake ids, replays."""
        return []

    def at_fuzz_start(self) -> None:
        """Note what the report compares against at the end (called once warmed up)."""

    def warmed_up(self) -> bool:
        """Whether the target works normally, beyond producing output (e.g. the OBU's clock is synced)."""
        return True

    def extra(self) -> dict:
        return {}

    # --- the run ------------------------------------------------------------------------------
    def run(self) -> dict:
        # compiled once per machine (v2i.core.jit: tens of seconds) here, not in each child
        load_kernels(RUN_KERNEL_MODULES)
        # from time zero: the warm-up, the sending (twice its time at the rate) and the settling, with a margin
        duration_s = WARM_UP_S + 2.0 * self.count / self.rate_hz + self.settle_s + 60.0
        try:
            for name, argv in self.argv(duration_s).items():
                self.children[name] = Child(name, argv)
            self.ready_s = wait_ready(self.children.values(), self.ready_timeout_s,
                                      f"v2i fuzz {self.name}" if self.progress is not None else None)
            victim = self.children[self.name].proc.pid
            self.open()  # subscribed before time zero
            start_ns = start_all(self.children.values())
            self._wait_for_output(start_ns)
            self._refused_at_start = self.refused()
            self.at_fuzz_start()
            before = rss_mb(victim)
            t0_ns = time.time_ns()
            crash = None
            try:
                if self.trickle:
                    self._trickle()
                else:
                    self._send_all()
                t1_ns = time.time_ns()
                self._sleep(self.settle_s)
            except Crashed as exc:
                crash, t1_ns = exc, time.time_ns()
            return self._report(t0_ns, t1_ns, before, rss_mb(victim), crash)
        finally:
            self.stop.set()
            for declared in self._declared:
                declared.undeclare()
            for session in self._sessions:
                session.close()
            for child in self.children.values():
                child.stop()

    def session(self, listen=(), connect=()):
        session = open_session(listen, connect)
        self._sessions.append(session)
        return session

    def declare(self, entity):
        self._declared.append(entity)
        return entity

    def output(self, t_ns: int, late: bool, mode: str | None = None) -> None:
        """A normal output of the target at ``t_ns`` (late if it missed its deadline; the OBU's
        fusion mode); any thread."""
        with self.lock:
            self.outputs.append((t_ns, late, mode))

    def _wait_for_output(self, start_ns: int, warm_up_s: float = WARM_UP_S) -> None:
        """Until the target's normal output flows and it is warmed up, at most ``warm_up_s`` after time
        zero ``start_ns``; DemoError saying what was missing after that."""
        deadline = time.monotonic() + (start_ns - time.time_ns()) * 1e-9 + warm_up_s
        while time.monotonic() < deadline:
            self._check_alive()
            with self.lock:
                flowing = len(self.outputs) >= FLOWING_OUTPUTS
            if time.time_ns() > start_ns and flowing and self.warmed_up():
                self.warm_up_s = (time.time_ns() - start_ns) * 1e-9
                return
            time.sleep(0.05)
        with self.lock:
            seen = len(self.outputs)
        raise DemoError(f"{self.name}: not working normally {warm_up_s:g} s after time zero ({seen} normal "
                        f"outputs of the {FLOWING_OUTPUTS} awaited; warmed up: {self.warmed_up()})")

    def _check_alive(self) -> None:
        for child in self.children.values():
            if child.proc.poll() is not None:
                raise Crashed(child.name, child.proc.returncode)

    def _sleep(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self._check_alive()
            time.sleep(0.05)

    def _send_all(self) -> None:
        """``count`` hostile messages at ``rate_hz``; progress on stderr every 5 s."""
        plan = self._plan()
        t_start = last_note = time.monotonic()
        for i in range(self.count):
            kind, send = next(plan)
            send()
            self.sent[kind] += 1
            if i % 64 == 0:
                self._check_alive()
                ahead_s = (i + 1) / self.rate_hz - (time.monotonic() - t_start)
                if ahead_s > 0:
                    time.sleep(ahead_s)
                if self.progress is not None and time.monotonic() - last_note > 5.0:
                    last_note = time.monotonic()
                    print(f"v2i fuzz {self.name}: {i + 1}/{self.count} sent", file=self.progress, flush=True)

    def _trickle(self) -> None:
        """The trickle against the target's listen endpoint for its duration, in a thread of its
        own while this one watches the services; each byte counts as one hostile message."""
        host, port = parse_endpoint(self.eps[self.trickle_target])
        done = threading.Event()
        result: dict = {}

        def trickle() -> None:
            try:
                result["counts"] = run_trickle(host, port, self.trickle, self.stop)
            except OSError as exc:  # out of file descriptors: said in the report
                result["error"] = str(exc)
            finally:
                done.set()

        if self.progress is not None:
            print(f"v2i fuzz {self.name}: trickle of {self.trickle.connections} connections to "
                  f"{self.eps[self.trickle_target]}, a byte every {self.trickle.byte_interval_s:g} s each, "
                  f"{self.trickle.duration_s:g} s", file=self.progress, flush=True)
        thread = threading.Thread(target=trickle, name="trickle", daemon=True)
        thread.start()
        try:
            while not done.wait(0.05):
                self._check_alive()
        finally:
            if not done.is_set():  # a service crashed: the trickle ends with the run
                self.stop.set()
            thread.join(timeout=5.0)
        counts = result.get("counts")
        self.trickled = {"connections": self.trickle.connections, "byte_interval_s": self.trickle.byte_interval_s,
                         **(counts.as_dict() if counts else {}), **({"error": result["error"]} if "error" in result else {})}
        self.sent[TRICKLE] = counts.bytes_sent if counts else 0

    def _plan(self):
        """An endless stream of (kind, send) over the target's inputs, shuffled each round."""
        now = time.time_ns()
        actions = []
        for kind, typ in itertools.product([k for k in self.kinds if k in KINDS], self.input_types):
            pool = itertools.cycle([self.hostile.make(kind, typ, now) for _ in range(POOL_PER_KIND)])
            actions.append((f"{kind}:{typ}", lambda typ=typ, pool=pool: self.deliver(typ, next(pool))))
        actions += self.special_actions() if "special" in self.kinds else []
        for k in itertools.count():
            if k % len(actions) == 0:
                self.rng.shuffle(actions)
            yield actions[k % len(actions)]

    def _report(self, t0_ns: int, t1_ns: int, before: float | None, after: float | None, crash) -> dict:
        window_s = (t1_ns - t0_ns) * 1e-9
        with self.lock:
            during = [late for t, late, _ in self.outputs if t0_ns <= t < t1_ns]
            modes = Counter(mode for t, _, mode in self.outputs if t0_ns <= t < t1_ns and mode is not None)
        expected = self.expected_outputs(window_s)
        refused = self.refused() - self._refused_at_start
        return {
            "target": self.name, "sent": sum(self.sent.values()), "sent_by_kind": dict(sorted(self.sent.items())),
            "rate_hz": round(sum(self.sent.values()) / max(window_s, 1e-9), 1), "fuzz_s": round(window_s, 2),
            "rejected": dict(sorted(refused.items())), "rejected_total": sum(refused.values()),
            "crashes": 0 if crash is None else 1, "crash": None if crash is None else str(crash),
            "outputs": {"expected": expected, "received": len(during), "late": sum(during),
                        "missing": max(expected - len(during), 0), **({"modes": dict(modes)} if modes else {})},
            "rss_mb": {"before": _r(before), "after": _r(after),
                       "growth": None if before is None or after is None else _r(after - before)},
            "startup": {"ready_s": _r(self.ready_s), "warm_up_s": _r(self.warm_up_s)},
            **({"trickle": self.trickled} if self.trickled is not None else {}),
            **self.extra(),
        }


def _r(v: float | None) -> float | None:
    return None if v is None else round(v, 1)


def summary(report: dict) -> str:
    """Human lines of a fuzz report."""
    o, r = report["outputs"], report["rss_mb"]
    top = ", ".join(f"{k} {v}" for k, v in sorted(report["rejected"].items(), key=lambda kv: -kv[1])[:8])
    return "\n".join([
        f"v2i fuzz {report['target']}: {report['sent']} {'bytes trickled' if 'trickle' in report else 'hostile messages'}"
        f" in {report['fuzz_s']} s "
        f"({report['rate_hz']}/s); crashes {report['crashes']}" + (f" ({report['crash']})" if report["crash"] else ""),
        f"  outputs during fuzzing: {o['received']}/{o['expected']} expected, {o['late']} late, {o['missing']} missing"
        + (f", {o['skipped']} skipped (their time had passed: a busy machine)" if o.get("skipped") else "")
        + (f"; modes {', '.join(f'{m} {n}' for m, n in sorted(o['modes'].items()))}" if "modes" in o else ""),
        *([f"  hostile files read {report['hostile_read']} of {report['sent']}"] if "hostile_read" in report else []),
        *([_trickle_line(report["trickle"])] if "trickle" in report else []),
        *([_genuine_line(report["genuine_lists"])] if "genuine_lists" in report else []),
        f"  RSS {r['before']} -> {r['after']} MB (growth {r['growth']} MB)",
        f"  refused {report['rejected_total']}: {top}",
    ])


def _trickle_line(t: dict) -> str:
    return (f"  trickle: {t['connections']} connections, a byte every {t['byte_interval_s']:g} s each: "
            f"{t.get('opens', 0)} opened, {t.get('reopens', 0)} reopened after the target closed them, "
            f"{t.get('refused', 0)} connects refused, {t.get('bytes_sent', 0)} bytes"
            + (f"; {t['error']}" if "error" in t else ""))


def _genuine_line(lists: dict) -> str:
    return f"  genuine RSU lists: {lists['accepted_by_obu']} accepted by the OBU of {lists['published']} published"
