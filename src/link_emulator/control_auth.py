"""Who may change a link: authentication of ``LinkControl`` messages.

Three modes, chosen at start-up (``LinkConfig.pki`` / ``insecure_control``):

- ``signed`` (``--pki DIR``): a control must be a signed envelope (:mod:`v2i.security.envelope`) for
  the key ``v2x/link/{link_id}/control``, from a certificate of DIR's CA whose role is
  ``operator`` and whose keys cover that key, generated at most ``max_age`` before and at most
  ``max_ahead`` after its receipt by the emulator's own clock, and never seen before (a per-signer
  replay window as long as ``max_age``). Rejections: the envelope verifier's reasons
  (``v2i.security.envelope.REJECTIONS``), ``wrong_role`` among them (a valid certificate of another
  role, e.g. an RSU's, even one issued with control keys: the verifier takes operators only).
- ``refuse`` (the default: no ``--pki``): every control is rejected as ``unauthenticated``.
- ``insecure`` (``--insecure-control``, lab only): unsigned control is accepted as before issue
  14; a signed one is unwrapped without any check.

Freshness window (defaults 2 s old, 0.5 s ahead): the controller signs right before it puts the
message, and the control session is a direct Zenoh hop (milliseconds, not the emulated radio),
so the window is mostly for the clock offset between the operator's host and the emulator's:
NTP keeps hosts of one site within tens of milliseconds, and 0.5 s ahead / 2 s old tolerates a
badly synchronised host while keeping a captured control useless 2 s later (and within those
2 s the replay window refuses it). Both are ``LinkConfig`` fields.

The revocation list is re-read (``v2i.security.trust_reload``: at most once per ``reload_s``, on a
control's arrival, if its file changed; a list that does not verify is refused and logged, the one
in force kept) so that revoking an operator needs no restart. Verification runs on the thread
that calls :meth:`ControlAuth.open` (the relay's scheduler thread) and never raises on any bytes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from schemas.codec import encode
from schemas.keys import link_control
from schemas.messages import LinkControl
from v2i.security.envelope import PREFIX, Signer, Verifier, parse, sign
from v2i.security.pki import Identity
from v2i.security.trust_reload import TrustReload

log = logging.getLogger(__name__)

OPERATOR = "operator"
NS_PER_S = 1_000_000_000
RELOAD_S = 1.0


def sign_control(control: LinkControl, identity: Identity | None, generation_ns: int) -> bytes:
    """``control`` in an envelope signed by ``identity`` at ``generation_ns`` (the controller's
    clock) for ``v2x/link/{link_id}/control``, always carrying the full certificate: controls are
    rare, and an emulator on another host need not hold the operator's ``.cert`` in advance.
    Without an identity, the bare encoding (an emulator with ``--insecure-control`` takes it)."""
    signer = None if identity is None else Signer(identity, cert_interval_ns=0)
    return sign(encode(control), signer, generation_ns, link_control(control.link_id))


@dataclass(frozen=True)
class Opened:
    """A control message after authentication: ``payload`` (the LinkControl bytes) when accepted,
    else None; ``reason`` ``ok``, ``unchecked`` (insecure mode) or the rejection; ``claimed``: the
    inner bytes, accepted or not (to report the message's seq with a rejection), None if unknown."""

    payload: bytes | None
    reason: str
    claimed: bytes | None


class ControlAuth:
    """Authenticates the link controls of one link; build with :meth:`create`. One owner thread."""

    def __init__(self, mode: str, link_id: str, directory: Path | None = None, max_age_s: float = 2.0,
                 max_ahead_s: float = 0.5, reload_s: float = RELOAD_S) -> None:
        if mode not in ("signed", "refuse", "insecure") or (mode == "signed") != (directory is not None):
            raise ValueError(f"control auth mode {mode!r} needs a PKI directory exactly when signed")
        self.mode, self.key_expr, self.directory = mode, link_control(link_id), directory
        self.max_age_ns, self.max_ahead_ns = round(max_age_s * NS_PER_S), round(max_ahead_s * NS_PER_S)
        self.verifier: Verifier | None = None
        self._trust: TrustReload | None = None
        if directory is not None:
            self._trust = TrustReload(directory, reload_s)  # PkiError on a bad directory
            self.verifier = Verifier(self._trust.trust, "strict", freshness_ns=self.max_age_ns,
                                     future_ns=self.max_ahead_ns, roles=(OPERATOR,))

    @classmethod
    def create(cls, link_id: str, pki: str | None, insecure: bool, max_age_s: float = 2.0,
               max_ahead_s: float = 0.5) -> ControlAuth:
        """The authenticator of a config: ``signed`` with a PKI directory (PkiError on a bad one),
        ``insecure`` when asked, else ``refuse``."""
        if pki is not None:
            return cls("signed", link_id, Path(pki), max_age_s, max_ahead_s)
        return cls("insecure" if insecure else "refuse", link_id, max_age_s=max_age_s, max_ahead_s=max_ahead_s)

    def describe(self) -> str:
        """One line for the start-up log."""
        if self.mode == "signed":
            return (f"link control: accepted when signed by an operator of the CA in {self.directory} "
                    f"(at most {self.max_age_ns / NS_PER_S:g} s old and {self.max_ahead_ns / NS_PER_S:g} s ahead "
                    "on arrival, each once)")
        if self.mode == "refuse":
            return ("link control is refused: no --pki DIR given, so every control is rejected as "
                    "'unauthenticated' (--insecure-control accepts unsigned control, lab only)")
        return "link control is NOT authenticated (--insecure-control, lab only): any peer may change the link"

    def open(self, data: bytes, receive_ns: int) -> Opened:
        """Authenticate the bytes received on the control key at ``receive_ns`` (emulator clock)."""
        data = bytes(data)
        env = parse(data)
        claimed = env.payload if env is not None else (None if data.startswith(PREFIX) else data)
        if self.mode == "insecure":
            return Opened(claimed, "unchecked", claimed)
        if self.mode == "refuse":
            return Opened(None, "unauthenticated", claimed)
        self._maybe_reload(receive_ns)
        payload, reason = self.verifier.verify(data, self.key_expr, receive_ns)
        return Opened(payload, reason, claimed)

    def explain(self, reason: str) -> str:
        """Why a control was rejected, for the stats' ``recent`` (what ``v2i link set`` prints)."""
        return {
            "unauthenticated": "this emulator was started without --pki, so it accepts no link control",
            "unsigned": "link control must be signed by an operator certificate (v2i link set --pki DIR)",
            "wrong_role": "signed by a certificate that is not an operator's",
            "stale": f"generated more than {self.max_age_ns / NS_PER_S:g} s before its receipt (a replay, or "
                     "the controller's clock is behind the emulator's)",
            "future": f"generated more than {self.max_ahead_ns / NS_PER_S:g} s after its receipt (the "
                      "controller's clock is ahead of the emulator's)",
            "replayed": "this signed control was already received",
            "unknown_cert": "signed by a certificate this emulator's CA did not issue",
            "revoked": "signed by a revoked certificate",
            "expired": "signed outside its certificate's validity",
            "wrong_key": f"the signer's certificate does not cover {self.key_expr}",
            "bad_signature": "the signature does not verify",
            "malformed": "not a well-formed signed envelope",
        }.get(reason, reason)

    # ---- the revocation list ----------------------------------------------------------------

    def _maybe_reload(self, now_ns: int) -> None:
        """Take a changed revocation list (checked once per reload_s); log what happened."""
        outcome = self._trust.poll(now_ns)
        if outcome is None:
            return
        if outcome.accepted:
            self.verifier.set_trust(outcome.trust)
        log.warning(outcome.describe())
