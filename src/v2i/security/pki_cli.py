"""``v2i pki``: the site CA on a directory, from the command line.

Thin shell over :mod:`.pki` and :mod:`.site` (the clock is read here, once per command):
``init`` a CA, ``issue`` a certificate, ``revoke`` one, ``list`` what the directory holds,
``site`` to fill a directory for a whole site in one go, ``attacker`` for the keys ``v2i attack``
holds (``v2i.security.attacker_keys``), and ``tls`` for the X.509 material of Zenoh TLS (``v2i.security.tls``, imported only by that command). Errors (a :class:`PkiError`, a bad
argument) are one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from v2i.security import algorithms as alg
from v2i.security.certificates import SIGNER_ROLES, CertificateError, check_key_expr
from v2i.security.attacker_keys import STOLEN_RSU, STOLEN_VEHICLE, prepare_attacker_pki, revoked_subject
from v2i.security.pki import CA_NAME, CRL_FILE, Pki, PkiError, load_trust, read_cert
from v2i.security.site import DEFAULT_DAYS, write_site

DESCRIPTION = """\
the site's certificate authority (CA) on a directory: create it, issue and revoke certificates.

Directory layout (every file written atomically; private keys mode 0600):
  ca.key, ca.cert        the site CA; ca.key signs certificates and the revocation list, so
                         keep it off the service hosts once the site is issued
  <subject>.key/.cert    one signing identity per RSU, vehicle or operator
  revoked.crl            the CA-signed revocation list (absent: nothing revoked)
Services load it with --pki DIR: a verifier needs ca.cert, revoked.crl and the others' *.cert
(pre-distributed certificates); a signer needs its own <subject>.key and <subject>.cert.

Roles (what a certificate may sign; its keys are the Zenoh key expressions it may publish on):
  rsu        object lists, predictions and time replies:  v2x/rsu/<subject>/**
  vehicle    a vehicle's own outputs:                    v2x/obu/<subject>/**
  operator   link emulator control (v2i link set, v2i chaos run): v2x/link/*/control
Subjects are the services' ids (an RSU's --rsu-id, a vehicle's --vehicle-id); 1-64 characters
of A-Z a-z 0-9 _ -.

A red-team exercise (v2i attack) needs keys an attacker could have stolen, issued by the site's
CA into DIR: v2i pki attacker DIR --rsu-id RSU_ID makes rsu-evil.key/.cert (a stolen RSU's),
stolen-vehicle.key/.cert (a stolen vehicle's) and RSU_ID-revoked.key/.cert (the victim RSU's
former certificate, covering v2x/rsu/RSU_ID/**), and revokes the last in revoked.crl. For a lab's
site only: the stolen keys are valid certificates of the site (v2i pki revoke them afterwards).

Zenoh TLS needs X.509 certificates instead: v2i pki tls DIR/tls NAME... writes a TLS CA and one
certificate per node into a directory of its own (v2i.security.tls).

examples:
  v2i pki site /etc/v2i/pki --rsu rsu1 --vehicle ego --operator operator
  v2i pki issue /etc/v2i/pki rsu2 --role rsu --days 90
  v2i pki revoke /etc/v2i/pki rsu2
  v2i pki list /etc/v2i/pki --json
  v2i pki attacker /tmp/lab-pki --rsu-id rsu1            # then: v2i attack ... --pki /tmp/lab-pki
"""


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add ``v2i pki``'s sub-commands to ``parser``."""
    parser.description = DESCRIPTION
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    sub = parser.add_subparsers(dest="pki_command", metavar="{init,issue,revoke,list,site,attacker,tls}",
                                required=True)
    _init_parser(_add(sub, "init", "create the site CA in DIR (refuses to overwrite one)"))
    _issue_parser(_add(sub, "issue", "issue a key pair and certificate for SUBJECT, signed by DIR's CA"))
    revoke = _add(sub, "revoke", "add SUBJECT's certificate to DIR's revocation list (re-signed by the CA)")
    revoke.add_argument("directory", metavar="DIR")
    revoke.add_argument("subject", metavar="SUBJECT")
    listing = _add(sub, "list", "list DIR's certificates: subject, role, keys, validity, digest, revoked")
    listing.add_argument("directory", metavar="DIR")
    listing.add_argument("--json", action="store_true", help="one JSON document on stdout instead of a table")
    _site_parser(_add(sub, "site", "a whole site in one go: the CA if absent, then every subject without a certificate"))
    _attacker_parser(_add(sub, "attacker", "the keys v2i attack holds, issued by DIR's CA: a stolen RSU and vehicle "
                          "key, and the victim RSU's former key, revoked"))
    tls = _add(sub, "tls", "X.509 CA, certificates and keys for Zenoh TLS / mutual TLS (v2i.security.tls)")
    tls.add_argument("directory", metavar="DIR")
    tls.add_argument("names", metavar="NAME[@IP,IP]", nargs="+",
                     help="a certificate per node: CN and DNS SAN NAME (what Zenoh's access control matches), "
                     "IP SANs for a node reached by address; use a directory of its own, e.g. PKI/tls")
    tls.add_argument("--days", type=_positive_days, default=DEFAULT_DAYS, help="validity (default %(default)s)")
    parser.set_defaults(func=run)


def _add(sub, name: str, text: str) -> argparse.ArgumentParser:
    return sub.add_parser(name, help=text, description=text)


def _init_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("directory", metavar="DIR", help="created if absent")
    p.add_argument("--days", type=_positive_days, default=3650.0, help="CA validity in days (default %(default)s)")
    p.add_argument("--algorithm", choices=alg.ALGORITHMS, default=alg.P256,
                   help="signature algorithm of the CA (default %(default)s)")
    p.add_argument("--ca-id", default="site-ca", help="the CA certificate's subject (default %(default)s)")


def _issue_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("directory", metavar="DIR")
    p.add_argument("subject", metavar="SUBJECT", help="the service's id, e.g. rsu1 or ego")
    p.add_argument("--role", required=True, choices=SIGNER_ROLES)
    p.add_argument("--keys", metavar="K", nargs="+", type=_key_expr,
                   help="key expressions it may publish on (default: the role's, see above)")
    p.add_argument("--days", type=_positive_days, default=365.0,
                   help="validity in days, capped at the CA's (default %(default)s)")
    p.add_argument("--algorithm", choices=alg.ALGORITHMS, help="signature algorithm (default: the CA's)")
    p.add_argument("--replace", action="store_true", help="re-issue (new key) if SUBJECT already has a certificate "
                   "(the old one stays valid until revoked: v2i pki revoke first if it leaked)")


def _site_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("directory", metavar="DIR")
    p.add_argument("--rsu", metavar="ID", nargs="+", default=[], help="RSU ids")
    p.add_argument("--vehicle", metavar="ID", nargs="+", default=[], help="vehicle ids")
    p.add_argument("--operator", metavar="NAME", nargs="+", default=["operator"],
                   help="operator names (default: operator)")
    p.add_argument("--days", type=_positive_days, default=DEFAULT_DAYS,
                   help="validity of a new CA and of new certificates (default %(default)s)")


def _attacker_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("directory", metavar="DIR", help="the site PKI (v2i pki site DIR ...): its CA issues the keys")
    p.add_argument("--rsu-id", default="rsu1", metavar="RSU_ID",
                   help="the victim RSU, v2i attack's --rsu-id: RSU_ID-revoked.key/.cert, its former certificate "
                        "covering v2x/rsu/RSU_ID/**, revoked in DIR/revoked.crl (default %(default)s)")
    p.add_argument("--stolen-rsu", default=STOLEN_RSU, metavar="S",
                   help="subject of the stolen RSU key, S.key/.cert covering v2x/rsu/S/** (default %(default)s)")
    p.add_argument("--stolen-vehicle", default=STOLEN_VEHICLE, metavar="S",
                   help="subject of the stolen vehicle key, S.key/.cert covering v2x/obu/S/** (default %(default)s)")
    p.add_argument("--days", type=_positive_days, default=DEFAULT_DAYS,
                   help="validity of new certificates (default %(default)s)")
    p.epilog = ("Existing keys are kept (idempotent). v2i attack --pki DIR --rsu-id RSU_ID --stolen S1,S2 reads "
                "them; the OBU and link emulator take the revocation within a second while they run. For a lab's "
                "site only: the stolen keys are valid certificates of the site (v2i pki revoke them afterwards).")


def _positive_days(text: str) -> float:
    value = float(text)
    if not 0.0 < value < 1e5:
        raise argparse.ArgumentTypeError(f"must be > 0 and < 100000 days, got {text}")
    return value


def _key_expr(text: str) -> str:
    try:
        return check_key_expr(text)
    except CertificateError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def run(args: argparse.Namespace) -> int:
    """Run one ``v2i pki`` command: 0 done, 2 on any PKI or argument error (one line on stderr)."""
    handler = {"init": _init, "issue": _issue, "revoke": _revoke, "list": _list, "site": _site,
               "attacker": _attacker, "tls": _tls}
    try:
        handler[args.pki_command](args, time.time_ns())
    except (PkiError, CertificateError, ValueError, OSError) as exc:
        reason = f"{exc.strerror}: {exc.filename}" if isinstance(exc, OSError) and exc.strerror else str(exc)
        print(f"v2i pki {args.pki_command}: {' '.join(reason.split())}", file=sys.stderr)
        return 2
    return 0


def _init(args: argparse.Namespace, now_ns: int) -> None:
    pki = Pki.init(args.directory, now_ns, days=args.days, ca_id=args.ca_id, algorithm=args.algorithm)
    ca = pki.ca.cert
    print(f"CA {ca.subject!r} ({ca.algorithm}) in {pki.directory}, valid until {_iso(ca.valid_until_ns)}, "
          f"digest {ca.digest.hex()}")


def _issue(args: argparse.Namespace, now_ns: int) -> None:
    pki = Pki.load(args.directory)
    cert = pki.issue(args.subject, args.role, now_ns, keys=args.keys, days=args.days,
                     algorithm=args.algorithm or pki.ca.cert.algorithm, replace=args.replace)
    print(f"{cert.subject}: {cert.role} ({cert.algorithm}), keys {', '.join(cert.keys)}, valid until "
          f"{_iso(cert.valid_until_ns)}, digest {cert.digest.hex()}")


def _revoke(args: argparse.Namespace, now_ns: int) -> None:
    cert = read_cert(Path(args.directory) / f"{args.subject}.cert")
    crl = Pki.load(args.directory).revoke(args.subject, now_ns)
    print(f"{args.subject}: revoked (digest {cert.digest.hex()}); {CRL_FILE} lists {len(crl.revoked)} "
          "certificate(s); a running OBU or link emulator with this --pki DIR takes it within a second")


def _site(args: argparse.Namespace, now_ns: int) -> None:
    directory = Path(args.directory)
    before = {p.stem for p in directory.glob("*.cert")}
    asked = [(s, "rsu") for s in args.rsu] + [(s, "vehicle") for s in args.vehicle] + \
        [(s, "operator") for s in args.operator]
    for subject, role in asked:
        if subject in before and (held := read_cert(directory / f"{subject}.cert").role) != role:
            raise PkiError(f"{directory / f'{subject}.cert'}: {subject!r} already holds a {held} certificate, "
                           f"asked for as {role}")
    write_site(directory, now_ns, args.rsu, args.vehicle, args.operator, days=args.days)
    for row in _rows(directory, now_ns):
        state = "kept" if row["file"] in before else "new"
        print(f"{state:5} {row['file']}: {row['role']} {row['subject']}, keys {', '.join(row['keys']) or '-'}")


def _attacker(args: argparse.Namespace, now_ns: int) -> None:
    directory = Path(args.directory)
    if not (directory / f"{CA_NAME}.cert").exists():
        raise PkiError(f"{directory}: no site CA ({CA_NAME}.cert) to issue the attacker's keys; make the site "
                       f"first: v2i pki site {directory} --rsu {args.rsu_id} --vehicle ego")
    made = prepare_attacker_pki(directory, now_ns, args.rsu_id, args.stolen_rsu, args.stolen_vehicle, args.days)
    for cert in made:
        print(cert.describe())
    stolen = f"{args.stolen_rsu},{args.stolen_vehicle}"
    print(f"{CRL_FILE} lists {len(load_trust(directory).revoked)} certificate(s), {revoked_subject(args.rsu_id)}'s "
          "among them; a running OBU and link emulator take it within a second")
    print(f"next: v2i attack --pki {directory} --rsu-id {args.rsu_id} --stolen {stolen} --connect OBU_EP "
          "--sniff RSU_EP [--control LINK_CONTROL_EP]")


def _tls(args: argparse.Namespace, now_ns: int) -> None:
    from v2i.security import tls  # the transport's X.509 material: only this command needs it

    for path in tls.issue_tls(args.directory, args.names, now_ns, args.days):
        print(f"wrote {path}")


def _rows(directory: Path, now_ns: int) -> list[dict[str, Any]]:
    """One row per ``*.cert`` of ``directory``, CA first; PkiError on a bad CA, list or certificate."""
    trust = load_trust(directory)
    rows = []
    for path in sorted(directory.glob("*.cert"), key=lambda p: (p.stem != CA_NAME, p.stem)):
        cert = read_cert(path)
        rows.append({
            "file": path.stem, "subject": cert.subject, "role": cert.role, "keys": list(cert.keys),
            "algorithm": cert.algorithm, "valid_from": _iso(cert.valid_from_ns), "valid_until": _iso(cert.valid_until_ns),
            "valid_now": cert.valid_at(now_ns), "digest": cert.digest.hex(), "revoked": cert.digest in trust.revoked,
            "issued_by_ca": cert.issuer == trust.ca.digest or path.stem == CA_NAME,
        })
    return rows


def _list(args: argparse.Namespace, now_ns: int) -> None:
    directory = Path(args.directory)
    if not directory.is_dir():
        raise PkiError(f"{directory}: no such directory")
    rows = _rows(directory, now_ns)
    if args.json:
        print(json.dumps({"directory": str(directory), "certificates": rows}, indent=2))
        return
    print(f"{'subject':16} {'role':9} {'valid from':20} {'valid until':20} {'digest':16} {'revoked':7} keys")
    for r in rows:
        note = ("" if r["valid_now"] else " (not valid now)") + ("" if r["issued_by_ca"] else " (other CA)")
        print(f"{r['subject']:16} {r['role']:9} {r['valid_from']:20} {r['valid_until']:20} {r['digest']:16} "
              f"{'yes' if r['revoked'] else 'no':7} {', '.join(r['keys']) or '-'}{note}")


def _iso(t_ns: int) -> str:
    """UTC time of ``t_ns`` to the second, e.g. 2026-11-24T10:00:00Z."""
    seconds = min(t_ns // 10**9, 253402300799)  # datetime stops at year 9999
    return datetime.fromtimestamp(seconds, tz=UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
