"""Runtime control of a link model (pure): what a LinkControl message does at a given time."""

from __future__ import annotations

from collections.abc import Callable

from schemas.codec import CodecError, decode
from schemas.messages import LinkControl

from link_emulator.channel import LinkModel
from link_emulator.control_auth import ControlAuth
from link_emulator.profile import bundled_profiles, load_profile

Reject = Callable[[str, "int | None", str], object]  # reason, control seq (None: undecodable), error


def admitted_control(data: bytes, link_id: str, reject: Reject, auth: ControlAuth, receive_ns: int) -> LinkControl | None:
    """The LinkControl in ``data`` if ``auth`` accepts it at ``receive_ns`` (``control_auth``), it
    decodes and names ``link_id``; else None, after ``reject(reason, seq, error)`` (the
    authentication's reason, ``codec_<reason>`` or ``wrong_link_id``). Never raises on any bytes."""
    opened = auth.open(data, receive_ns)
    if opened.payload is None:
        reject(opened.reason, _claimed_seq(opened.claimed), auth.explain(opened.reason))
        return None
    payload = opened.payload
    try:
        control = decode(payload, LinkControl)
    except CodecError as exc:
        reject(f"codec_{exc.reason}", None, str(exc))
        return None
    if control.link_id != link_id:
        reject("wrong_link_id", control.seq, f"link_id {control.link_id!r}, this emulator is {link_id!r}")
        return None
    return control


def _claimed_seq(claimed: bytes | None) -> int | None:
    """The seq a rejected control claims (so that its sender learns the outcome), None if unreadable."""
    if claimed is None:
        return None
    try:
        return decode(claimed, LinkControl).seq
    except CodecError:
        return None


def apply_control(model: LinkModel, control: LinkControl, now_ns: int) -> str:
    """Apply ``control`` to ``model`` as of ``now_ns``; returns a one-line description.

    Raises ValueError for a profile that is not bundled (nothing is changed then).
    """
    if control.profile is not None:
        if control.profile not in bundled_profiles():
            raise ValueError(f"unknown profile {control.profile!r}; bundled: {', '.join(bundled_profiles())}")
        model.switch_profile(load_profile(control.profile))
        return f"profile switched to {control.profile}"
    if control.clear:
        model.clear_impairments()
        return "impairments cleared"
    end_ns = now_ns + round(control.duration_s * 1e9)
    model.add_impairment(now_ns, end_ns, control.direction, outage=control.outage,
                         extra_delay_ms=control.extra_delay_ms, loss_probability=control.loss_probability,
                         bandwidth_kbps=control.bandwidth_kbps)
    effects = (["outage"] if control.outage else []) + \
        ([f"+{control.extra_delay_ms:g} ms"] if control.extra_delay_ms else []) + \
        ([f"loss {control.loss_probability:g}"] if control.loss_probability is not None else []) + \
        ([f"{control.bandwidth_kbps:g} kbit/s"] if control.bandwidth_kbps is not None else [])
    return f"{', '.join(effects)} on {control.direction} for {control.duration_s:g} s"
