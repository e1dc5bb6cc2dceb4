"""``v2i link set``: change a running link emulator through its control endpoint.

Builds one ``LinkControl`` from the options (:func:`control_from_action`, pure), signs it with an
operator identity of the site PKI when given (``--pki DIR``; :func:`control_auth.sign_control`),
puts it on ``v2x/link/{link_id}/control`` at the emulator's ``--control-listen`` endpoint and waits
for the emulator's stats to report that message's ``seq`` applied or rejected (:func:`send_control`).
"""

from __future__ import annotations

import argparse
import json
import queue
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

import zenoh
from pydantic import ValidationError

from schemas.keys import check_id, link_control, link_stats
from schemas.messages import LinkControl
from v2i.runtime.transport import open_session
from v2i.security.pki import Identity, PkiError, load_signer

from link_emulator.control_auth import OPERATOR, sign_control

SET_DESCRIPTION = """\
change a running link emulator through its control endpoint.

The emulator must have been started with --control-listen EP (v2i demo and v2i chaos run
give it one); this command connects there, waits until the emulator is reachable, puts one
LinkControl message on v2x/link/{link_id}/control and waits for the emulator's stats to
report it applied. Exit status: 0 applied, 1 not reachable / rejected / not confirmed in
time, 2 bad arguments (or a PKI that cannot be loaded).

An emulator started with --pki applies only control signed by an operator certificate of its
CA: give --pki DIR (a directory holding <identity>.key and <identity>.cert, e.g. from
v2i pki site; --identity NAME, default operator). The signature carries this host's clock:
keep it within 0.5 s ahead / 2 s behind the emulator's (NTP does). An emulator started without
--pki refuses every control unless it was started with --insecure-control (lab only).

Exactly one action:
  --profile NAME             switch to a bundled profile (names only, no files)
  --clear                    remove every impairment
  --outage S                 drop every message for S seconds
  --delay-spike MS --for S   add MS of delay for S seconds
  --loss P --for S           lose messages with probability P for S seconds
  --bandwidth KBPS --for S   cap the send rate at KBPS kbit/s for S seconds
Impairments act on --direction (default both) from their receipt on; impairments of a
killed and restarted emulator are gone. Every action applies to every vehicle's channel of
an emulator serving several, or with --vehicle ID to that vehicle's only.

examples:
  v2i link set --connect tcp/127.0.0.1:7450 --pki /etc/v2i/pki --outage 10
  v2i link set --connect tcp/127.0.0.1:7450 --delay-spike 300 --for 2 --direction downlink
  v2i link set --connect tcp/127.0.0.1:7450 --clear
  v2i link set --connect tcp/127.0.0.1:7450 --vehicle car2 --loss 1 --for 5
"""


def configure_set_parser(parser: argparse.ArgumentParser) -> None:
    """Options of ``v2i link set``; see ``SET_DESCRIPTION``."""
    parser.add_argument("--connect", metavar="EP", action="append", required=True,
                        help="the emulator's control endpoint (its --control-listen), e.g. tcp/127.0.0.1:7450")
    parser.add_argument("--link-id", default="link1", help="the emulator's link id (default %(default)s)")
    parser.add_argument("--vehicle", dest="vehicle_id", metavar="ID",
                        help="act on this vehicle's channel only (default: every vehicle's)")
    action = parser.add_mutually_exclusive_group(required=True)
    action.add_argument("--profile", metavar="NAME", help="switch to this bundled profile")
    action.add_argument("--clear", action="store_true", help="remove every impairment")
    action.add_argument("--outage", metavar="S", type=positive_seconds, help="link down for S seconds")
    action.add_argument("--delay-spike", metavar="MS", type=float, help="extra delay in ms (with --for)")
    action.add_argument("--loss", metavar="P", type=float, help="loss probability 0..1 (with --for)")
    action.add_argument("--bandwidth", metavar="KBPS", type=float, help="send rate cap in kbit/s (with --for)")
    parser.add_argument("--for", dest="for_s", metavar="S", type=positive_seconds,
                        help="duration of --delay-spike, --loss or --bandwidth, s")
    parser.add_argument("--direction", choices=["uplink", "downlink", "both"], default="both",
                        help="direction of an impairment (default %(default)s)")
    parser.add_argument("--pki", metavar="DIR", help="sign the control with an operator identity of this site PKI "
                        "directory (needed by an emulator started with --pki)")
    parser.add_argument("--identity", metavar="NAME", default=OPERATOR,
                        help="with --pki: the signing identity, DIR/NAME.key and DIR/NAME.cert (default %(default)s)")
    parser.add_argument("--timeout", metavar="S", type=positive_seconds, default=5.0,
                        help="seconds to wait for the emulator, and again for its confirmation (default %(default)s)")
    parser.set_defaults(func=run_set)


@dataclass(frozen=True)
class SetAction:
    """What ``v2i link set`` was asked to do (the action options, unvalidated)."""

    profile: str | None = None
    clear: bool = False
    outage_s: float | None = None
    delay_spike_ms: float | None = None
    loss_probability: float | None = None
    bandwidth_kbps: float | None = None
    for_s: float | None = None
    direction: str = "both"
    vehicle_id: str | None = None


def control_from_action(link_id: str, action: SetAction, seq: int = 0) -> LinkControl:
    """The LinkControl message for ``action`` (pure); ValueError naming the option if it is wrong."""
    timed = {"--delay-spike": action.delay_spike_ms, "--loss": action.loss_probability,
             "--bandwidth": action.bandwidth_kbps}
    given = [name for name, value in timed.items() if value is not None]
    if given and action.for_s is None:
        raise ValueError(f"{given[0]} needs --for S (how long it lasts)")
    if not given and action.for_s is not None:
        raise ValueError("--for applies to --delay-spike, --loss and --bandwidth only")
    fields: dict = {"link_id": link_id, "seq": seq, "vehicle_id": action.vehicle_id}
    if action.profile is not None:
        fields["profile"] = action.profile
    elif action.clear:
        fields["clear"] = True
    elif action.outage_s is not None:
        fields.update(outage=True, duration_s=action.outage_s, direction=action.direction)
    else:
        fields.update(duration_s=action.for_s, direction=action.direction, extra_delay_ms=action.delay_spike_ms or 0.0,
                      loss_probability=action.loss_probability, bandwidth_kbps=action.bandwidth_kbps)
    try:
        return LinkControl(**fields)
    except ValidationError as exc:
        first = exc.errors(include_url=False)[0]
        where = ".".join(str(p) for p in first["loc"])
        raise ValueError(f"{where}: {first['msg']}" if where else first["msg"]) from None


def run_set(args: argparse.Namespace) -> int:
    """``v2i link set``: 0 when the emulator confirmed the change, 1 when it did not, 2 on bad arguments."""
    action = SetAction(args.profile, args.clear, args.outage, args.delay_spike, args.loss, args.bandwidth,
                       args.for_s, args.direction, args.vehicle_id)
    try:
        check_id(args.link_id)
        control = control_from_action(args.link_id, action, seq=time.time_ns() % 2**63)
        identity = _identity(args.pki, args.identity) if args.pki is not None else None
    except (ValueError, PkiError) as exc:
        print(f"link set: {exc}", file=sys.stderr)
        return 2
    try:
        result = send_control(args.connect, control, args.timeout, identity)
    except ControlError as exc:
        print(f"link set: {exc}", file=sys.stderr)
        return 1
    print(f"link {args.link_id}: {result}")
    return 0


class ControlError(RuntimeError):
    """A control message that the emulator did not confirm: unreachable, rejected or too slow."""


def _identity(directory: str, subject: str) -> Identity:
    """The signing identity ``subject`` of ``directory``; PkiError unless it is an operator's."""
    identity = load_signer(directory, subject)
    if identity.cert.role != OPERATOR:
        raise PkiError(f"{directory}/{subject}.cert: a {identity.cert.role} certificate; link control needs an "
                       f"{OPERATOR}'s (v2i pki issue DIR NAME --role operator)")
    return identity


def send_control(connect: list[str], control: LinkControl, timeout_s: float, identity: Identity | None = None) -> str:
    """Put ``control`` to the emulator at ``connect`` and return its description of the change.

    Signed by ``identity`` (at this host's clock, right before the put) when given, else sent
    unsigned. Waits (up to ``timeout_s`` each) for the emulator's control subscriber, then for
    a stats message reporting this message's ``seq`` applied or rejected (``control.recent``).
    Raises ControlError otherwise.
    """
    stats: queue.Queue[dict] = queue.Queue()
    session = open_session(connect=connect)
    try:
        sub = session.declare_subscriber(link_stats(control.link_id), lambda s: _queue_json(stats, s))
        pub = session.declare_publisher(link_control(control.link_id))
        try:
            if not _wait_until(lambda: pub.matching_status.matching, timeout_s):
                raise ControlError(f"no link emulator {control.link_id!r} reachable at {', '.join(connect)} "
                                   f"within {timeout_s:g} s (is it running with --control-listen there?)")
            pub.put(sign_control(control, identity, time.time_ns()))
            return _confirmation(stats, control.seq, timeout_s)
        finally:
            pub.undeclare()
            sub.undeclare()
    finally:
        session.close()


def _queue_json(into: queue.Queue, sample: zenoh.Sample) -> None:
    try:
        into.put(json.loads(sample.payload.to_bytes()))
    except ValueError:
        pass  # not a stats message of ours


def _wait_until(condition: Callable[[], bool], timeout_s: float, poll_s: float = 0.02) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() >= deadline:
            return False
        time.sleep(poll_s)
    return True


def _confirmation(stats: queue.Queue, seq: int, timeout_s: float) -> str:
    """The emulator's description of message ``seq`` from its stats; ControlError if rejected or silent."""
    deadline = time.monotonic() + timeout_s
    while (remaining_s := deadline - time.monotonic()) > 0:
        try:
            control = stats.get(timeout=remaining_s).get("control") or {}
        except queue.Empty:
            break
        outcome = next((o for o in control.get("recent", []) if o.get("seq") == seq), None)
        if outcome is not None and "result" in outcome:
            return outcome["result"]
        if outcome is not None:
            raise ControlError(f"the emulator rejected it ({outcome['rejected']}): {outcome['error']}")
    raise ControlError(f"the emulator did not confirm the change within {timeout_s:g} s")


def positive_seconds(text: str) -> float:
    """argparse type: a duration in seconds > 0."""
    value = float(text)
    if not value > 0.0:
        raise argparse.ArgumentTypeError(f"must be > 0 seconds, got {text}")
    return value
