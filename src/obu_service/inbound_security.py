"""What the OBU lets through from the RSUs' signed messages (pure; the node and the evaluator share it).

Every RSU object list (any wire), prediction list and time reply is verified
(``v2i.security.envelope.Verifier``) before anything decodes it:

- freshness is judged in the *signer's* clock: ``now_rsu_ns = receive_ns + theta_hat``, theta_hat
  the OBU's offset estimate of that RSU (theta = rsu - obu) at the receive time. Before the first
  estimate there is no such clock and only the replay window applies (``now_ns=None``);
- a time reply is never judged fresh or stale (it carries its own exchange: the pipeline matches
  it to its request by the echoed t1 and seq), only signed, covered and not replayed.

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
from v2i.security.envelope import REJECTIONS, Verifier
from v2i.security.pki import PkiError, Trust
from v2i.security.trust_reload import TrustReload

FUTURE_S = 1.0  # how far ahead of the estimated RSU clock a generation time may be
ClockOffset = Callable[[str, int], "object | None"]  # (rsu_id, obu t_ns) -> estimate with .offset_ns, or None


class InboundSecurity:
    """Verifies RSU messages for one OBU; ``reject(label)`` counts each failure."""

    def __init__(self, verifier: Verifier, clock_offset: ClockOffset, reject: Callable[[str], None],
                 reload: TrustReload | None = None):
        self.verifier = verifier
        self._clock_offset = clock_offset
        self._reject = reject
        self._reload = reload  # the --pki directory's revocation list, watched while running (None: not watched)
        self.verified = False  # whether the last message opened was signed and verified (``open``)

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
        return payload

    def _rsu_now_ns(self, key_expr: str, receive_ns: int) -> int | None:
        """The receive time on the sending RSU's clock, or None before its clock is estimated."""
        rsu_id = rsu_id_or_none(key_expr)
        estimate = None if rsu_id is None else self._clock_offset(rsu_id, receive_ns)
        return None if estimate is None else receive_ns + round(estimate.offset_ns)


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
                  reject: Callable[[str], None]) -> InboundSecurity:
    """A live OBU's gate: ``pki_dir``'s trust under ``policy`` (:func:`make_verifier`), its revocation
    list watched while running unless nothing is checked (no directory, or policy off); ValueError
    naming a bad file."""
    try:
        reload = None if pki_dir is None else TrustReload(pki_dir)
    except PkiError as exc:
        raise ValueError(str(exc)) from None
    verifier = make_verifier(None if reload is None else reload.trust, policy, freshness_s)
    return InboundSecurity(verifier, clock_offset, reject, None if policy == "off" else reload)
