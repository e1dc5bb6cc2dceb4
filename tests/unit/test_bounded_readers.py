"""Every reader of a file v2i is handed refuses what is not a regular file under its limit, at
once and by its own error type (v2i.core.files underneath): scenario, link profile, chaos
timeline, site and its map, PKI, calibration, detector model, trace, Zenoh config, wire file,
MCAP recording, camera video and image frames."""

from __future__ import annotations

import gzip
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from v2i.core.files import MiB


@pytest.fixture
def hostile(tmp_path, alarm):
    """name -> (a symlink to /dev/zero, a FIFO), each with that name's suffix."""
    def make(suffix: str) -> tuple[str, str]:
        zero, fifo = tmp_path / f"zero{suffix}", tmp_path / f"fifo{suffix}"
        zero.symlink_to("/dev/zero")
        os.mkfifo(fifo)
        return str(zero), str(fifo)

    return make


def _both_refused(paths, load, error, match=r"(a character device|a FIFO); a \w"):
    for path in paths:
        with pytest.raises(error, match=match):
            load(path)


def test_yaml_data_files_refuse_devices_and_fifos(hostile):
    from link_emulator.profile import ProfileError, load_profile
    from v2i.offline.chaos import ChaosError, load_chaos
    from v2i.sim.scenario import ScenarioError, load_scenario

    paths = hostile(".yaml")
    _both_refused(paths, load_scenario, ScenarioError, r"scenario .*(a character device|a FIFO); a scenario must be "
                                                       r"a regular file of at most 4 MiB")
    _both_refused(paths, load_profile, ProfileError, "of at most 1 MiB")
    _both_refused(paths, load_chaos, ChaosError, "of at most 1 MiB")


def test_an_oversized_scenario_is_refused_unread(tmp_path):
    from v2i.sim.scenario import ScenarioError, load_scenario

    big = tmp_path / "big.yaml"
    with open(big, "wb") as f:
        f.truncate(4 * MiB + 1)
    with pytest.raises(ScenarioError, match=f"{4 * MiB + 1} bytes; a scenario must be a regular file of at most 4 MiB"):
        load_scenario(big)


def test_a_site_map_that_is_a_fifo_is_named(tmp_path, alarm):
    from v2i.runtime.site import SiteError, load_site

    os.mkfifo(tmp_path / "map.osm")
    (tmp_path / "site.yaml").write_text("name: s\norigin: {lat_deg: 49.0, lon_deg: 8.4}\n"
                                        "vehicles: [{id: ego, size_m: [4.6, 1.9, 1.5]}]\nmap: map.osm\n")
    with pytest.raises(SiteError, match="map: cannot read Lanelet2 map .*map.osm: a FIFO"):
        load_site(tmp_path / "site.yaml")


def test_lanelet2_maps_are_checked_before_lanelet2_opens_them(hostile):
    pytest.importorskip("lanelet2")
    from v2i.core.files import FileRefused
    from v2i.fusion.lane_prediction import LanePredictor

    _both_refused(hostile(".osm"), lambda p: LanePredictor.from_osm(p, 49.0, 8.4), FileRefused,
                  "a Lanelet2 map must be a regular file of at most 64 MiB")


def test_pki_files_are_bounded_and_a_key_mode_comes_from_its_descriptor(tmp_path, alarm):
    from v2i.security.pki import PkiError, load_signer, load_trust, read_crl
    from v2i.security.site import write_site

    site = write_site(tmp_path / "pki", 10**18, rsu_ids=["rsu1"])
    load_trust(site), load_signer(site, "rsu1")
    (site / "ca.cert").unlink()
    (site / "ca.cert").symlink_to("/dev/zero")
    with pytest.raises(PkiError, match="certificate .*ca.cert: a character device; a certificate must be a regular "
                                       "file of at most 64 KiB"):
        load_trust(site)
    os.mkfifo(site / "revoked.crl")
    with pytest.raises(PkiError, match="revoked.crl: a FIFO; a revocation list must be a regular file of at most 1 MiB"):
        read_crl(site, None, None)  # refused before anything is decoded
    (site / "rsu1.key").chmod(0o644)
    with pytest.raises(PkiError, match="accessible by others"):
        load_signer(site, "rsu1")


def test_calibration_model_and_trace(hostile, tmp_path):
    from link_emulator.trace import TraceError, load_trace
    from v2i.perception.calibration import CalibrationError, load_calibration
    from v2i.perception.detector import DetectorModelError, OnnxDetector

    _both_refused(hostile(".json"), load_calibration, CalibrationError, "a calibration must be a regular file")
    _both_refused(hostile(".onnx"), OnnxDetector, DetectorModelError, "a detector model must be a regular file of at most "
                                                                  "512 MiB")
    _both_refused(hostile(".txt"), load_trace, TraceError, "a trace must be a regular file of at most 64 MiB")
    bomb = tmp_path / "bomb.txt.gz"  # 65 MiB of text in ~65 kB
    bomb.write_bytes(gzip.compress(b"0" * (65 * MiB), compresslevel=1))
    with pytest.raises(TraceError, match="over 64 MiB decompressed"):
        load_trace(str(bomb))


def test_zenoh_config_and_wire_files(hostile):
    from v2i.runtime.transport import read_config_file
    from v2i.wire_cli import decode_file

    _both_refused(hostile(".json5"), read_config_file, ValueError, "a Zenoh config must be a regular file of at most "
                                                                   "1 MiB")
    for path in hostile(".uper"):
        result = decode_file(Path(path), "cpm")
        assert not result["ok"] and "a message file must be a regular file of at most 1 MiB" in result["reason"]


def test_recordings_and_videos_must_be_regular_files(hostile, tmp_path):
    from rsu_service.recording import ImageFrames
    from rsu_service.recording import RecordingError as VideoError
    from v2i.telemetry.mcap_reader import Recording, RecordingError

    _both_refused(hostile(".mcap"), Recording, RecordingError, "a recording must be a regular file$")
    _both_refused(hostile(".mp4"), ImageFrames, VideoError, "a video must be a regular file$")


def test_image_frames_that_are_devices_or_fifos_are_refused_and_counted(tmp_path, alarm):
    from rsu_service.recording import ImageFrames

    cv2.imwrite(str(tmp_path / "00.png"), np.full((8, 8, 3), 10, np.uint8))
    (tmp_path / "01.png").symlink_to("/dev/zero")  # st_size 0: passed the old size check, then read forever
    os.mkfifo(tmp_path / "02.png")
    frames = ImageFrames(tmp_path)
    got = [frames.next() for _ in range(3)]
    assert got[0] is not None and got[1] is None and got[2] is None
    assert frames.refused["unreadable"] == 2 and frames.read == 1
