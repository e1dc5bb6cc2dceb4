"""The keys a red-team exercise gives its attacker (``v2i pki attacker``, ``v2i attack``), in the site PKI.

The lab, holding the site CA, issues into the site's directory what an attacker near an RSU could
have got hold of, so that ``v2i attack`` tests the verifiers with genuine site certificates:

    <stolen RSU>.key/.cert      (default ``rsu-evil``) an RSU certificate of the site: its keys cover
                                ``v2x/rsu/rsu-evil/**``, not the victim's (the ``wrong_key`` kind)
    <stolen vehicle>.key/.cert  (default ``stolen-vehicle``) a vehicle certificate (``wrong_role`` at the
                                OBU and the emulator's control, ``wrong_key`` elsewhere)
    <RSU>-revoked.key/.cert     a former certificate of the victim RSU itself, covering its keys
                                ``v2x/rsu/<RSU>/**``, added to ``revoked.crl`` (the ``revoked`` kind:
                                only the revocation list stops it)

The attacker's own key of the ``forged`` kind is made in memory by each run (no certificate names
it), and replays are captured off the air, so nothing else needs a file. Certificates are valid
from an hour before their issue, for ``days`` after it. Times are arguments.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from schemas.keys import check_id

from v2i.security import certificates as certs
from v2i.security.pki import CA_NAME, NS_PER_DAY, Identity, Pki, PkiError, load_signer, load_trust, read_cert

STOLEN_RSU, STOLEN_VEHICLE = "rsu-evil", "stolen-vehicle"
BACKDATE_NS = 3600 * 10**9  # attacker certificates are valid from an hour before preparation


def revoked_subject(rsu_id: str) -> str:
    """Subject of the victim RSU's former, revoked certificate."""
    return f"{check_id(rsu_id)}-revoked"


@dataclass(frozen=True)
class AttackerCert:
    """One certificate of the attacker's in the directory: ``new`` (issued now) or kept from before."""

    subject: str
    role: str
    keys: tuple[str, ...]
    new: bool
    revoked: bool
    use: str  # what ``v2i attack`` does with it

    def describe(self) -> str:
        """One line: state, files, role, keys, use."""
        state = "new" if self.new else "kept"
        revoked = ", revoked in revoked.crl" if self.revoked else ""
        return (f"{state:5} {self.subject}.key/.cert: {self.role}, keys {', '.join(self.keys)}{revoked} "
                f"({self.use})")


def prepare_attacker_pki(directory: str | Path, now_ns: int, rsu_id: str, stolen_rsu: str = STOLEN_RSU,
                         stolen_vehicle: str = STOLEN_VEHICLE, days: float = 30.0) -> list[AttackerCert]:
    """Issue (if absent) the keys the attacker will have stolen and the victim RSU's former key,
    and revoke the latter: the lab's part, done with the CA (a new one when ``directory`` has none).
    Idempotent; returns what the directory holds for the attacker; PkiError on bad files."""
    directory = Path(directory)
    pki = Pki.load(directory) if (directory / f"{CA_NAME}.cert").exists() else Pki.init(directory, now_ns)
    old = revoked_subject(rsu_id)
    stolen = "stolen: signs the attack kinds wrong_key, time and control"
    wanted = ((stolen_rsu, "rsu", None, stolen), (stolen_vehicle, "vehicle", None, stolen),
              (old, "rsu", certs.default_keys("rsu", rsu_id), f"{rsu_id}'s former key: signs the attack kind revoked"))
    made = []
    for subject, role, key_exprs, use in wanted:
        new = not (directory / f"{subject}.cert").exists()
        if new:
            pki.issue(subject, role, now_ns - BACKDATE_NS, keys=key_exprs, days=days + BACKDATE_NS / NS_PER_DAY)
        made.append((subject, new, use))
    if read_cert(directory / f"{old}.cert").digest not in load_trust(directory).revoked:
        pki.revoke(old, now_ns)
    revoked = load_trust(directory).revoked
    certificates = [(read_cert(directory / f"{subject}.cert"), new, use) for subject, new, use in made]
    return [AttackerCert(c.subject, c.role, c.keys, new, c.digest in revoked, use) for c, new, use in certificates]


@dataclass(frozen=True)
class AttackerKeys:
    """The keys the attacker holds: stolen ones (not covering the victim's keys) and a revoked one."""

    stolen: tuple[Identity, ...]
    revoked: Identity


def load_attacker_keys(directory: str | Path, rsu_id: str,
                       stolen: tuple[str, ...] = (STOLEN_RSU, STOLEN_VEHICLE)) -> AttackerKeys:
    """The attacker's identities from ``directory`` (see :func:`prepare_attacker_pki`); PkiError
    naming the missing or bad file."""
    if not stolen:
        raise PkiError("the attacker needs at least one stolen key")
    return AttackerKeys(tuple(load_signer(directory, s) for s in stolen),
                        load_signer(directory, revoked_subject(rsu_id)))
