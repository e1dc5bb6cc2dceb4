"""V2V (pure): what a vehicle shares with its peers, and how it takes in theirs.

What a vehicle shares (``shared_list``), like the perceived objects of an ETSI CPM sent by a
vehicle: only the objects its *own* sensors perceive (wire ``sources`` has ``SOURCE_VEHICLE``;
the tracker sets that bit while its LiDAR updated the track within ``max_coast_s``), never what
it knows only from RSUs or peers, so lists do not echo from car to car and get counted twice.
The message is the OBU's ``FusedObjectList`` restricted to those objects: positions in the
sender's ``base_link`` at ``cycle_time_ns`` (its own LiDAR capture, *sender clock*), with the
sender's ego pose in ``map`` in the header, so the receiver computes T_map<-base = [R(yaw) | t]
from the header alone (a CPM's reference position and heading). Keys (``schemas.keys``):
``v2x/v2v/{sender}/objects``. The key names the sender; the V2V emulator relays a vehicle's
``v2x/v2v/{that vehicle}/**`` only, so one vehicle cannot speak for another through it.

How the receiver learns the sender's clock: the same NTP-style four-timestamp exchange the
OBU runs with RSUs. Each OBU broadcasts a ``TimeRequest`` (t1, own clock) on
``v2x/v2v/{me}/time``; every peer answers with a ``TimeReply`` (t2 receive, t3 send, its clock)
on ``v2x/v2v/{peer}/time_reply/{me}`` (``answer``), both through the V2V channels, so the
exchange sees the radio's delays. Replies are matched and held by ``TimeRequests``
(conflicting replies void each other) and filtered per peer by ``ClockSync`` (low-delay
samples, drift); theta = peer clock - own clock. The error left is at most half the delay
asymmetry of the samples kept (``OffsetEstimate.uncertainty_ns``); vehicles' clocks being
GNSS-disciplined in a real V2X stack, theta is close to 0 there and the exchange bounds it.
Measured in the offline runner (``v2i.offline.runner``, vehicles on one true clock, so the
estimate *is* the error) and reported per vehicle and peer.

How the receiver uses a peer's list (``PeerIntake.on_list``), screened like an RSU's
(``obu_service.admission``, refusals counted as ``v2v_<reason>`` in the pipeline's ``rejected``):
the sender id in the key must equal the header's (``v2v_key_mismatch``); a list of this very
vehicle is refused (``v2v_self``: no vehicle ever fuses its own objects back); frame
``base_link`` only (``v2v_bad_frame``); a bounded peer table (``max_peers`` slots, unknown ids
evicted like unknown RSUs, forgotten after ``rsu_expiry_s``; ``v2v_too_many_peers``); object
count, duplicates, future and stale stamps once the peer's clock is known; objects not marked
as the sender's own perception are dropped (``v2v_not_own_perception``: the receiver does not
rely on the sender's filtering); then the objects go base_link -> map with the header's pose,
those off the site or on this vehicle itself (the peer sees us) are dropped, and each peer's
objects get the peer's own source bit (a *peer slot*, after the RSU slots in the tracker's
bits, ``v2i.fusion.tracking.slot_source``) and ids ``RSU_ID_BASE * (slot + 1) + id``.

Fusion: a peer's lists are tracker estimates like an RSU's (covariance intersection where
another source's estimate shares the track, ``v2i.fusion.tracking``). Peers' cycles are not
aligned with ours (each runs on its own LiDAR), so their lists are fused inter-frame in every
cycle (newest of each peer, each list once, predicted to the cycle time), whatever mode the
RSU data put the cycle in; the mode policy stays about RSUs. So no link statistics are kept per
peer (an RSU's ``LinkMonitor`` serves the intra mode's wait and the metrics; nothing reads a peer's).
"""

from __future__ import annotations

import dataclasses
from collections import Counter

import numpy as np
from pydantic import ValidationError

from v2i.core.frames import Pose2D, base_to_map
from v2i.core.identity_memo import IdentityMemo
from v2i.core.objects import ObjectArray, read_only
from v2i.fusion.pose_history import PoseHistory
from v2i.fusion.tracking import slot_source
from v2i.fusion.wire import objects_from_states
from schemas.columns import ObjectColumns
from schemas.messages import SOURCE_VEHICLE, FusedObjectList, ObjectListHeader, TimeReply, TimeRequest

from obu_service.admission import Admission
from v2i.clock.clock_sync import OffsetEstimate
from obu_service.methods import RsuFrame
from obu_service.mode_inputs import ModeInputs, Received
from obu_service.rsu_table import MAX_RSUS, RSU_ID_BASE, RsuState, RsuTable
from v2i.clock.time_requests import TimeRequests

MAX_PEERS = 8  # peer slots (tracker source bits) an OBU gives to V2V peers by default
PEER_REPLY_NS = 50_000  # an OBU's time between receiving a peer's time request and answering it (offline)


def shared_list(out: FusedObjectList) -> FusedObjectList:
    """What a vehicle shares of its fused output ``out``: the objects its own sensors perceive
    (``SOURCE_VEHICLE`` in ``sources``), same header (sender clock, base_link, ego pose)."""
    cols = out.objects
    own = (cols.column("sources") & SOURCE_VEHICLE) != 0  # (N,) bool, one mask over the sources column
    if own.all():
        return out
    # a row subset of validated, canonical codes is itself valid: no per-object model, no re-validation
    return out.model_copy(update={"objects": ObjectColumns(cols.codes[own], fused=True)})


def answer(request: TimeRequest, me: str, t2_ns: int, t3_ns: int) -> TimeReply:
    """This OBU's reply to a peer's time request: t2 receive, t3 send (own clock), t1 echoed."""
    return TimeReply(rsu_id=me, seq=request.seq, t1_ns=request.t1_ns, t2_ns=t2_ns, t3_ns=t3_ns)


class _Prefixed:
    """Counts written as ``prefix + reason`` into ``target`` (what ``Admission`` counts for peers)."""

    RENAMED = {"too_many_rsus": "too_many_peers", "unknown_rsu": "unknown_peer"}

    def __init__(self, target: Counter, prefix: str):
        self._target, self._prefix = target, prefix

    def _key(self, reason: str) -> str:
        return self._prefix + self.RENAMED.get(reason, reason)

    def __getitem__(self, reason: str) -> int:
        return self._target[self._key(reason)]

    def __setitem__(self, reason: str, value: int) -> None:
        self._target[self._key(reason)] = value


class PeerIntake:
    """The peers an OBU hears over V2V: their clocks, lists and slots (see the module docstring).

    ``rejected``: the pipeline's counter (refusals land there as ``v2v_<reason>``); ``poses``:
    the pipeline's own ego poses; ``first_slot``: the first tracker slot after the RSUs'.
    """

    def __init__(self, config, rejected: Counter, poses: PoseHistory, first_slot: int, max_peers: int = MAX_PEERS):
        if not 1 <= max_peers or first_slot + max_peers > MAX_RSUS:
            raise ValueError(f"V2V: {max_peers} peer slots after {first_slot} RSU slots exceed the "
                             f"{MAX_RSUS} cooperative source bits")
        self.me = config.vehicle_id
        self.rejected = _Prefixed(rejected, "v2v_")
        self.poses = poses
        self.table = RsuTable({}, max_peers, round(config.rsu_expiry_s * 1e9), True, first_index=first_slot)
        self._admission = Admission(config.limits(), self.table, self.rejected, link_stats=False)
        # peers are always fused inter-frame: place and consume their lists as in the adaptive mode
        self._inputs = ModeInputs(dataclasses.replace(config, fusion_mode="adaptive"), self.table)
        self._requests = TimeRequests(self.me)
        self._frames_kept = config.frames_kept

    # --- clocks ----------------------------------------------------------------------
    def make_time_request(self, t1_ns: int) -> TimeRequest:
        """A request to broadcast to every peer now (t1 = own send time)."""
        return self._requests.make(t1_ns)

    def answer(self, request: TimeRequest, sender: str, t2_ns: int, t3_ns: int) -> TimeReply | None:
        """The reply to a peer's request heard on ``v2x/v2v/{sender}/time``, or None (counted)."""
        if request.obu_id != sender:
            self.rejected["time_request_key_mismatch"] += 1
            return None
        if sender == self.me:
            self.rejected["self"] += 1
            return None
        return answer(request, self.me, t2_ns, t3_ns)

    def on_time_reply(self, reply: TimeReply, answerer: str, t4_ns: int) -> None:
        """A peer's reply heard on ``v2x/v2v/{answerer}/time_reply/{me}``."""
        if reply.rsu_id != answerer or answerer == self.me:
            self.rejected["time_reply_key_mismatch" if reply.rsu_id != answerer else "self"] += 1
            return
        refused = self._requests.match(reply, t4_ns)
        if refused is not None:
            self.rejected[refused] += 1
        self._sync(t4_ns)

    def _sync(self, now_ns: int) -> None:
        for peer, sample in self._requests.ripe(now_ns):
            state = self.table.admit(peer, sample.t4_ns)
            if isinstance(state, str):
                self.rejected[state] += 1
            elif not state.sync.add(sample):
                self.rejected["time_reply_inconsistent"] += 1

    def clock_offset(self, peer: str, t_ns: int) -> OffsetEstimate | None:
        """theta = peer clock - own clock at own time ``t_ns``; None before sync."""
        state = self.table.get(peer)
        return None if state is None else state.sync.estimate_at(t_ns)

    # --- lists -----------------------------------------------------------------------
    def on_list(self, msg: FusedObjectList, sender: str, receive_ns: int) -> bool:
        """Take a peer's shared list heard on ``v2x/v2v/{sender}/objects``; False if refused (counted)."""
        self._sync(receive_ns)
        reason = ("key_mismatch" if msg.vehicle_id != sender else "self" if sender == self.me
                  else "bad_frame" if msg.frame_id != "base_link" else None)
        header = None if reason is not None else _header(msg)
        if header is None:
            self.rejected[reason or "bad_header"] += 1
            return False
        state = self._admission.lists(header, len(msg.objects), receive_ns)
        if state is None:
            return False
        state.lists_seen.add((header.seq, header.capture_time_ns))
        objects, not_own = _own_in_map(msg)
        if not_own:
            self.rejected["not_own_perception"] += not_own
        objects = self._admission.on_site(state, objects, self.poses.at(receive_ns, uncertainty=False))
        est = state.sync.estimate_at(receive_ns)
        capture_ns = receive_ns if est is None else est.to_obu_ns(header.capture_time_ns)
        objects = self._admission.not_ego(objects, self.poses.at(capture_ns, uncertainty=False))
        objects = objects.with_(ids=_slot_ids(state, objects.ids),
                                sources=np.full(len(objects), slot_source(state.index), np.int64))
        state.frames.append(Received(header.capture_time_ns, header.valid_time_ns, header.seq, objects, receive_ns))
        state.accepted += 1
        state.last_receive_ns = receive_ns
        while len(state.frames) > self._frames_kept:
            state.frames.popleft()
        return True

    # --- fusion ----------------------------------------------------------------------
    def frames(self, t_c: int) -> tuple[list[RsuFrame], list[RsuFrame]]:
        """(newest list of each peer, lists not yet fused) usable at cycle time ``t_c``."""
        self._sync(t_c)
        self.table.expire(t_c)
        return self._inputs.inter(t_c)

    def consume(self, fused: list[RsuFrame], t_c: int) -> None:
        """Mark the peer lists fed to the tracker (each list is a measurement once)."""
        self._inputs.consume(fused, t_c)

    def summary(self, t_ns: int) -> dict[str, dict]:
        """Per peer: lists accepted, slot, clock offset estimate and its uncertainty (ms) at ``t_ns``."""
        out = {}
        for state in self.table:
            est = state.sync.estimate_at(t_ns)
            out[state.rsu_id] = {
                "slot": state.index, "lists_accepted": state.accepted,
                "clock_offset_ms": None if est is None else est.offset_ns * 1e-6,
                "clock_uncertainty_ms": None if est is None else est.uncertainty_ns * 1e-6,
                "sync_samples": 0 if est is None else est.samples,
            }
        return out


@IdentityMemo
def _header(msg: FusedObjectList) -> ObjectListHeader | None:
    """The list's header in the RSU lists' terms (capture = the sender's cycle time), for admission
    (once per list: the same for every receiver)."""
    try:
        return ObjectListHeader(rsu_id=msg.vehicle_id, seq=msg.seq, capture_time_ns=msg.cycle_time_ns,
                                publish_time_ns=msg.publish_time_ns, frame_id="map")
    except ValidationError:  # published before captured
        return None


@IdentityMemo
def _own_in_map(msg: FusedObjectList) -> tuple[ObjectArray, int]:
    """(the list's objects its sender perceives itself, base_link -> map with the header's pose
    (read-only, shared), how many others it carried): once per list, the same for every receiver."""
    objects = objects_from_states(msg.objects)
    own = (objects.sources & SOURCE_VEHICLE) != 0
    not_own = 0 if own.all() else int((~own).sum())
    if not_own:
        objects = objects.take(own)
    objects = base_to_map(objects, Pose2D(msg.ego_x, msg.ego_y, msg.ego_yaw), pose_uncertainty=False)
    return read_only(objects), not_own


def _slot_ids(state: RsuState, ids: np.ndarray) -> np.ndarray:
    """Output ids of a slot's objects: RSU_ID_BASE * (slot + 1) + id mod base (as RSU objects)."""
    return RSU_ID_BASE * (state.index + 1) + np.mod(ids, RSU_ID_BASE)
