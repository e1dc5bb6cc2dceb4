"""The security side of a live run (``v2i demo``, ``chaos run``, the site demo): one site PKI for every
process, and each service's flags.

The PKI is always written (the link emulator's control needs an operator certificate whatever the
run signs); ``RunSpec.security`` decides whether the RSUs sign (``--pki``) and how the OBUs verify
(``--pki DIR --security POLICY``). None: nothing is signed.
"""

from __future__ import annotations

from pathlib import Path

from v2i.security.site import write_site
from v2i.sim.scenario import Scenario

from v2i.offline.spec import RunSpec


def run_pki(spec: RunSpec, scenario: Scenario, directory: str | Path, now_ns: int) -> Path:
    """``directory`` completed as the PKI of the run's site: every RSU and vehicle of ``scenario`` and the
    single RSU and vehicle ids the two-node demo runs as (``spec``'s service configs), the operator."""
    rsu_ids = dict.fromkeys([spec.rsu_config().rsu_id, *(r.id for r in scenario.rsus)])
    vehicle_ids = dict.fromkeys([spec.obu_config().vehicle_id, *(v.name for v in scenario.vehicles)])
    return write_site(directory, now_ns, rsu_ids, vehicle_ids)


def security_argv(spec: RunSpec, service: str, pki_dir: Path) -> list[str]:
    """``service``'s (rsu, obu, link) signing / verification flags in this run."""
    if spec.security is None or service not in ("rsu", "obu"):
        return []
    return ["--pki", str(pki_dir)] + (["--security", spec.security] if service == "obu" else [])
