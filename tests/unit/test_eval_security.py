"""The offline runner signs and verifies as the live services do (RunSpec.security)."""

from dataclasses import replace

from v2i.offline.runner import OfflineRun
from v2i.offline.spec import RunSpec
from v2i.security.envelope import Signer

SPEC = RunSpec(scenario="red-light-runner", seed=2, duration_s=8.0)


def _scores(report: dict) -> dict:
    return {k: v for k, v in report.items() if k not in ("security", "security_outcomes")}


def _run(spec: RunSpec, tamper=None) -> dict:
    run = OfflineRun(spec)
    if tamper is not None:
        tamper(run)
    run.execute()
    return run.report()


def test_strict_verifies_every_genuine_message_and_changes_no_score():
    off, strict = _run(replace(SPEC, security="off")), _run(replace(SPEC, security="strict"))
    assert _scores(strict) == _scores(off)
    outcomes = strict["security_outcomes"]["ego"]
    assert set(outcomes) == {"ok"} and outcomes["ok"] > 100  # lists, predictions, time replies: all verified
    assert off["security_outcomes"]["ego"] == {"unchecked": outcomes["ok"]}
    assert _run(SPEC)["security_outcomes"] is None


def test_strict_drops_an_rsu_signing_with_a_vehicle_certificate_as_wrong_role():
    def vehicle_signs_for_the_rsu(run: OfflineRun) -> None:  # key substitution: a valid cert of the wrong holder
        run.rsus[0].signer = Signer(run.identities["ego"])

    spec = replace(SPEC, security="strict")
    report = _run(spec, vehicle_signs_for_the_rsu)
    outcomes = report["security_outcomes"]["ego"]
    assert set(outcomes) == {"wrong_role"} and outcomes["wrong_role"] > 100  # the OBU takes RSU certificates only
    assert report["rsu_messages_received"] == 0
    assert report["obu_rejected"]["security_wrong_role"] == outcomes["wrong_role"]  # what the OBU's metrics count
    permissive = _run(replace(spec, security="permissive"), vehicle_signs_for_the_rsu)
    assert permissive["rsu_messages_received"] > 0  # counted, and fused anyway
