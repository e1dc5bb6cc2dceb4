"""What the OBU lets through from the RSUs' signed messages (pure; the node and the evaluator share it).

Every RSU object list (any wire), prediction list and time reply is verified
(``v2i.security.envelope.Verifier``) before anything decodes it:

- freshness is judged in the *signer's* clock: ``now_rsu_ns = receive_ns + theta_hat``, theta_hat
  the OBU's offset estimate of that RSU (theta = rsu - obu) at the receive time. Before the first
  estimate there is no such clock and only the replay window applies (``now_ns=None``);
- a time reply is never judged fresh or stale (it carries its own exchange: the pipeline matches
  it to its request by the echoed t1 and seq), only signed, covered and not replayed.

Then the rate budget of *that signer*: a token bucket per verified certificate and key
(``SIGNER_RATE_HZ`` sustained, ``SIGNER_BURST`` at once, the OBU's ``source_rate_hz`` / ``source_burst``);
over it the message is dropped as ``signer_rate_limited``. A genuine RSU's budget is drawn by its own
messages only: what does not verify never reaches it (the live intake bounds what fails verification
with a separate budget: ``v2i.runtime.intake``, ``unverified_budget``). Under ``off`` nothing is verified
and the intake's per-key budget applies instead.

Outcomes are counted through ``reject(label)``: ``security_<reason>`` for a drop (``strict``, and
``malformed`` under ``permissive``), ``security_accepted_<reason>`` for a failure ``permissive``
let through. Under ``off`` (no ``--pki``) envelopes are unwrapped unchecked and unsigned bytes pass
unchanged, as before signing existed.

A live OBU (:func:`live_security`) also takes a revocation while it runs: its node calls
:meth:`InboundSecurity.poll_trust` from its loop after each cycle's output (never per message), which
looks at ``DIR/revoked.crl`` at most once a second (``v2i.security.trust_reload``); a new list signed by the
CA applies from the next message on (the revoked RSU's messages dropped as ``security_revoked``), one
that does not parse, is not the CA's or is older than the list in force is refused and logged.
"""

from __future__ import annotations

from collections.abc import Callable

from schemas.keys import rsu_id_or_none
from v2i.runtime.intake import KeyedBuckets
from v2i.security.envelope import PREFIX, REJECTIONS, Verifier
from v2i.security.pki import PkiError, Trust
from v2i.security.trust_reload import TrustReload

FUTURE_S = 1.0  # how far ahead of the estimated RSU clock a generation time may be
# a verified signer's budget per key: an RSU sends 5-10 lists, paths and time replies a second on each key
SIGNER_RATE_HZ, SIGNER_BURST = 50.0, 25
SILENT_S = 10.0  # messages received and none verified this long: warn (a wrong CA?)
ClockOffset = Callable[[str, int], "object | None"]  # (rsu_id, obu t_ns) -> estimate with .offset_ns, or None


class InboundSecurity:
    """Verifies RSU messages for one OBU; ``reject(label)`` counts each failure."""

    def __init__(self, verifier: Verifier, clock_offset: ClockOffset, reject: Callable[[str], None],
                 reload: TrustReload | None = None, signer_rate_hz: float = SIGNER_RATE_HZ,
                 signer_burst: int = SIGNER_BURST):
        self.verifier = verifier
        self._clock_offset = clock_offset
        self._reject = reject
        self._reload = reload  # the --pki directory's revocation list, watched while running (None: not watched)
        self._budgets = KeyedBuckets(signer_rate_hz, signer_burst)  # per (verified signer, key)
        self.verified = False  # whether the last message opened was signed and verified (``open``)
        self._silence = _Silence(round(SILENT_S * 1e9))

    @property
    def checks(self) -> bool:
        """Whether messages are verified at all (not under policy ``off``)."""
        return self.verifier.policy != "off"

    def poll_trust(self, now_ns: int) -> str | None:
        """Between messages: take a changed revocation list (looked at once a second at most); the
        log line of what was taken or refused, None when nothing changed."""
        outcome = None if self._reload is None else self._reload.poll(now_ns)
        if outcome is None:
            return None
        if outcome.accepted:
            self.verifier.set_trust(outcome.trust)
        return outcome.describe()

    def open(self, data: bytes, key_expr: str, receive_ns: int, time_reply: bool = False) -> bytes | None:
        """The payload to decode, or None when the message is dropped (counted)."""
        # (policy off reads no time: no clock estimate asked for a check that is not made)
        unchecked = time_reply or self.verifier.policy == "off"
        now_ns = None if unchecked else self._rsu_now_ns(key_expr, receive_ns)
        payload, reason = self.verifier.verify(data, key_expr, now_ns)
        self.verified = reason == "ok"  # the last message's signature checked against the site's trust
        if reason in REJECTIONS:
            self._reject(("security_" if payload is None else "security_accepted_") + reason)
        self._silence.note(receive_ns, self.verified, reason)
        if self.verified and not self._budgets.take((self.verifier.last_signer, key_expr), receive_ns):
            self._reject("signer_rate_limited")
            return None
        return payload

    def silence_warning(self, now_ns: int) -> str | None:
        """Once per silence: a warning when messages kept coming for ``SILENT_S`` and none verified
        (likely the wrong CA in --pki); None otherwise (and always under policy ``off``)."""
        return self._silence.warning(now_ns) if self.checks else None

    def _rsu_now_ns(self, key_expr: str, receive_ns: int) -> int | None:
        """The receive time on the sending RSU's clock, or None before its clock is estimated."""
        rsu_id = rsu_id_or_none(key_expr)
        estimate = None if rsu_id is None else self._clock_offset(rsu_id, receive_ns)
        return None if estimate is None else receive_ns + round(estimate.offset_ns)


def envelope_screen(policy: str) -> Callable[[bytes], str | None]:
    """What the live intake refuses before queueing (``v2i.runtime.intake``, ``screen``): under ``strict``,
    bytes without an envelope (``security_unsigned``, a check of 4 bytes: the verifier would drop them
    first thing); under the other policies nothing."""
    if policy != "strict":
        return lambda data: None
    return lambda data: None if data.startswith(PREFIX) else "security_unsigned"


class _Silence:
    """Whether anything received verified lately: the failures since the last verified message
    (or the first message), by reason, and when they began."""

    def __init__(self, after_ns: int):
        self.after_ns = after_ns
        self._since_ns: int | None = None  # first failure since the last verified message
        self._reasons: dict[str, int] = {}
        self._warned = False

    def note(self, receive_ns: int, verified: bool, reason: str) -> None:
        if verified:
            self._since_ns, self._reasons, self._warned = None, {}, False
            return
        if self._since_ns is None:
            self._since_ns = receive_ns
        if len(self._reasons) < 16 or reason in self._reasons:
            self._reasons[reason] = self._reasons.get(reason, 0) + 1

    def warning(self, now_ns: int) -> str | None:
        if self._warned or self._since_ns is None or now_ns - self._since_ns < self.after_ns:
            return None
        self._warned = True
        reasons = ", ".join(f"{r} {n}" for r, n in sorted(self._reasons.items(), key=lambda rn: -rn[1]))
        hint = "; --pki may hold another site's CA" if "unknown_cert" in self._reasons else ""
        return (f"WARNING: nothing received verified for {(now_ns - self._since_ns) / 1e9:.0f} s "
                f"({sum(self._reasons.values())} refused: {reasons}){hint}")


def make_verifier(trust: Trust | None, policy: str, freshness_s: float) -> Verifier:
    """The OBU's verifier: ``trust`` (None: only ``off`` works) under ``policy``.

    Freshness = ``freshness_s``, the oldest RSU data the pipeline would still use (its planning
    horizon): anything older is refused by the pipeline anyway, so the window costs nothing genuine.
    A generation time up to FUTURE_S ahead of the estimated RSU clock passes (a clock step not yet
    tracked); the pipeline's own, finer future check still applies. Only RSU certificates are taken
    (``wrong_role`` otherwise), whatever keys a certificate names.
    """
    return Verifier(trust, policy, freshness_ns=round(freshness_s * 1e9), future_ns=round(FUTURE_S * 1e9),
                    roles=("rsu",))


def live_security(pki_dir: str | None, policy: str, freshness_s: float, clock_offset: ClockOffset,
                  reject: Callable[[str], None], signer_rate_hz: float = SIGNER_RATE_HZ,
                  signer_burst: int = SIGNER_BURST) -> InboundSecurity:
    """A live OBU's gate: ``pki_dir``'s trust under ``policy`` (:func:`make_verifier`), its revocation
    list watched while running unless nothing is checked (no directory, or policy off), each verified
    signer's budget ``signer_rate_hz`` / ``signer_burst`` per key; ValueError naming a bad file."""
    try:
        reload = None if pki_dir is None else TrustReload(pki_dir)
    except PkiError as exc:
        raise ValueError(str(exc)) from None
    verifier = make_verifier(None if reload is None else reload.trust, policy, freshness_s)
    return InboundSecurity(verifier, clock_offset, reject, None if policy == "off" else reload, signer_rate_hz,
                           signer_burst)
