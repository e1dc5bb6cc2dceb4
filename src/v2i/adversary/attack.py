"""``v2i attack``: an attacker near an RSU against a live site, and what got through.

Sessions (one per endpoint: the attacker never bridges the RSU and vehicle sides):
- ``--sniff EP`` (the RSU's endpoint: its radio broadcast, heard by anyone near it): genuine
  object lists of ``--rsu-id``, for replays, the RSU's certificate digest and clock (generation
  time minus local receive time), and the genuine objects the ghost rule must not confuse;
- ``--connect EP`` (the OBU's): sends the attack lists on ``v2x/rsu/{rsu_id}/objects``, answers
  the OBU's time queries on ``v2x/rsu/{rsu_id}/time`` with forged replies (kind ``time``: each
  query gets a burst of ``--time-burst`` replies), and reads ``v2x/obu/{vid}/pose``,
  ``.../objects`` and ``.../metrics``;
- ``--control EP`` (the emulator's control endpoint, optional): the link outages (kind
  ``control``) and the emulator's ``v2x/link/{id}/stats``.

Kinds (``v2i.adversary.attack_messages``) run one after another, ``--count`` each at ``--rate-hz``,
each followed by ``--settle-s``; the opt-in kinds against the genuine RSU's share
(``v2i.adversary.attack_hostile``: ``flood`` for ``--flood-s`` at ``--flood-rate-hz``, the time
relays ``time_doubled`` and ``time_delayed`` for ``--time-s``) report what the genuine RSU lost; the OBU's and the emulator's rejection counters grown over a
kind's phase are what it caused. Before the first kind, ``--warmup-s`` of genuine traffic with
*decoy* ghost placements measures the ghost rule's false positives (``v2i.adversary.attack_ghosts``).
Callbacks only enqueue (a bounded queue; drops counted), except the time queryable, which must
answer in its callback. Exit 0 when nothing got through, 1 when something did (or the site
never became ready), 130 on Ctrl-C (a partial report is printed), 2 on bad input.
"""

from __future__ import annotations

import argparse
import json
import shlex
import signal
import sys

from v2i.security.attacker_keys import STOLEN_RSU, STOLEN_VEHICLE

from v2i.adversary.attack_messages import ALL_KINDS, HOSTILE_KINDS, KINDS, RELAY_KINDS


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.description = ("Attack a running v2i site as someone near the RSU would: ghost pedestrians 8 m ahead of the "
                     "ego (unsigned, forged, signed with stolen or revoked keys), replays of captured genuine "
                     "lists, forged time replies and link-control outages (opt-in: a flood on the genuine RSU's key and relays of "
                     "its own time replies, doubled or delayed); report per kind what the OBU and the "
                     "link emulator rejected (by reason), what they let through, and whether a ghost reached the "
                     "fused output. v2i demo logs the endpoints. Exit 1 when anything got through. First make the "
                     "attacker's keys in the site PKI the services use: v2i pki attacker DIR --rsu-id RSU_ID (a "
                     "stolen RSU and vehicle key, and the RSU's former key, revoked; a running OBU and link emulator "
                     "take the revocation within a second).")
    p.add_argument("--connect", required=True, metavar="EP", help="the OBU's endpoint (its --listen)")
    p.add_argument("--sniff", required=True, metavar="EP", help="the RSU's endpoint: its broadcast, captured")
    p.add_argument("--control", metavar="EP", help="the link emulator's control endpoint (kind control)")
    p.add_argument("--pki", required=True, metavar="DIR",
                   help="the site PKI (v2i pki site) holding the attacker's keys, made by v2i pki attacker DIR "
                        "--rsu-id RSU_ID; this reads, for each --stolen subject S, S.key and S.cert (a stolen RSU "
                        "and vehicle certificate of the site), and RSU_ID-revoked.key and .cert (the victim RSU's "
                        "former certificate, revoked in DIR/revoked.crl). The OBU and link emulator must verify with "
                        "this DIR's CA and revocation list (their --pki DIR, or a copy of revoked.crl on their host)")
    p.add_argument("--stolen", default=f"{STOLEN_RSU},{STOLEN_VEHICLE}", metavar="S1,S2",
                   help="subjects of the stolen keys in --pki, as made by v2i pki attacker (default %(default)s)")
    p.add_argument("--rsu-id", default="rsu1", help="the victim RSU (default %(default)s)")
    p.add_argument("--vehicle-id", default="ego", help="the OBU's vehicle (default %(default)s)")
    p.add_argument("--link-id", default="link1", help="the emulator's link id (default %(default)s)")
    p.add_argument("--kinds", default=",".join(KINDS), metavar="K1,K2",
                   help="default, in this order: %(default)s. Opt-in, timed, against the genuine RSU's share of the "
                        "OBU (each reports what the genuine RSU lost): flood (junk, unsigned and forged lists on the "
                        "RSU's own objects key at --flood-rate-hz for --flood-s: its lists sent and accepted, ghosts, "
                        "output misses, cycles by mode), time_doubled (each OBU time query relayed to the genuine RSU, "
                        "its signed replies returned twice) and time_delayed (the query held --time-delay-ms first), "
                        "each for --time-s: the OBU's clock samples, steps, offset and uncertainty, cycles by mode")
    p.add_argument("--count", type=int, default=1000, help="messages per kind (default %(default)s)")
    p.add_argument("--rate-hz", type=float, default=30.0,
                   help="messages per second (default %(default)s: the OBU takes 50/s per key, burst 25, and the "
                        "genuine RSU uses 5-10 of them; faster, its rate limit refuses attack and genuine lists alike)")
    p.add_argument("--time-burst", type=int, default=3, help="forged replies per time query (the OBU asks 10 times "
                   "a second; default %(default)s)")
    p.add_argument("--flood-rate-hz", type=float, default=500.0,
                   help="kind flood: messages per second (default %(default)s; the rate reached is reported)")
    p.add_argument("--flood-s", type=float, default=20.0, help="kind flood: seconds (default %(default)s)")
    p.add_argument("--time-s", type=float, default=40.0,
                   help="kinds time_doubled and time_delayed: seconds each (default %(default)s)")
    p.add_argument("--time-delay-ms", type=float, default=100.0,
                   help="kind time_delayed: how long each OBU time query is held before it is forwarded to the RSU "
                        "(default %(default)s)")
    p.add_argument("--from-start", action="store_true",
                   help="run the first kind (time_doubled or time_delayed) from the moment the attacker's sessions "
                        "are open, without waiting for the site's traffic: start the attack before the site's start "
                        "line, once it printed {\"event\": \"ready\"} on stdout, so that it meets the OBU's first "
                        "time query")
    p.add_argument("--ready-timeout", type=float, default=120.0, metavar="S",
                   help="seconds the site may take to show what the attack needs: the RSU's signed lists, the ego's "
                        "pose, OBU metrics with a clock estimate and accepted lists (default %(default)s; a progress "
                        "line names what is awaited)")
    p.add_argument("--warmup-s", type=float, default=3.0, help="genuine-only window before the attack (default %(default)s)")
    p.add_argument("--settle-s", type=float, default=1.5, help="wait after each kind (default %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="seed of the attacker's choices (default %(default)s)")
    p.add_argument("--json", metavar="PATH", help="write the report JSON to PATH ('-' for stdout)")


def run(args: argparse.Namespace) -> int:
    from schemas.keys import check_id
    from v2i.security.pki import PkiError

    from v2i.security.attacker_keys import load_attacker_keys
    from v2i.adversary.attack_report import format_report, got_through

    kinds = check_kinds(args)
    for name in (args.rsu_id, args.vehicle_id, args.link_id):
        check_id(name)
    stolen = tuple(s for s in args.stolen.split(",") if s)
    try:
        attacker = load_attacker_keys(args.pki, args.rsu_id, stolen)
    except PkiError as exc:
        hint = prepare_command(args.pki, args.rsu_id, stolen)
        raise ValueError(f"--pki: {exc}; make the attacker's keys with: {hint}") from None
    from v2i.adversary.attack_live import AttackRun, NotReady

    attack = AttackRun(args, kinds, attacker)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _interrupt)
    code = 0
    try:
        report = attack.run()
    except NotReady as exc:
        print(f"v2i attack: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("v2i attack: interrupted; the report so far:", file=sys.stderr)
        report, code = attack.report(), 130
    finally:
        attack.close()
    _emit(report, args.json, format_report(report))
    return code or (1 if got_through(report) else 0)


def check_kinds(args: argparse.Namespace) -> list[str]:
    """The ``--kinds`` to run, in order; ValueError naming the bad option otherwise."""
    kinds = [k.strip() for k in args.kinds.split(",") if k.strip()]
    unknown = sorted(set(kinds) - set(ALL_KINDS))
    if unknown or not kinds:
        raise ValueError(f"--kinds: unknown {', '.join(unknown) or '(none given)'}; kinds: {', '.join(KINDS)}; "
                         f"opt-in: {', '.join(HOSTILE_KINDS)}")
    if len(set(kinds)) != len(kinds):
        raise ValueError(f"--kinds: each kind once (got {args.kinds})")
    if "control" in kinds and not args.control:
        raise ValueError("kind control needs --control EP (the link emulator's control endpoint)")
    if args.count < 1 or not 0 < args.rate_hz <= 10_000 or args.time_burst < 1 or not args.ready_timeout > 0:
        raise ValueError("--count and --time-burst must be >= 1, --rate-hz in (0, 10000] and --ready-timeout > 0")
    if not (0 < args.flood_rate_hz <= 20_000 and 0 < args.flood_s <= 3600 and 0 < args.time_s <= 3600
            and 0 <= args.time_delay_ms <= 10_000):
        raise ValueError("--flood-rate-hz must be in (0, 20000], --flood-s and --time-s in (0, 3600], "
                         "--time-delay-ms in [0, 10000]")
    if args.from_start and kinds[0] not in RELAY_KINDS:
        raise ValueError(f"--from-start: the first kind must be a time relay ({', '.join(RELAY_KINDS)}), "
                         f"not {kinds[0]}")
    return kinds


def prepare_command(pki_dir: str, rsu_id: str, stolen: tuple[str, ...]) -> str:
    """The ``v2i pki attacker`` command line that makes what this attack reads."""
    extra = [] if stolen == (STOLEN_RSU, STOLEN_VEHICLE) else \
        [arg for flag, s in zip(("--stolen-rsu", "--stolen-vehicle"), stolen) for arg in (flag, s)]
    return shlex.join(["v2i", "pki", "attacker", pki_dir, "--rsu-id", rsu_id, *extra])


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def _emit(report: dict, json_path: str | None, table: str) -> None:
    if json_path == "-":
        print(json.dumps(report, indent=2))
        print(table, file=sys.stderr)
        return
    print(table)
    if json_path:
        with open(json_path, "w") as out:
            out.write(json.dumps(report, indent=2) + "\n")
