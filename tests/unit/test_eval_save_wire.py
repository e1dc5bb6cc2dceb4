"""``v2i eval --save-wire DIR``: every list an RSU broadcasts is saved as sent (before any signature), in
send order, and each decodes with v2i's decoders; saving changes nothing of the run."""

import json

import pytest

from schemas.list_wire import decode_list
from v2i.cli import main
from v2i.offline.runner import OfflineRun
from v2i.offline.spec import RunSpec
from v2i.security.envelope import unwrap

SUFFIX = {"v2i": "v2i.msgpack", "cpm": "cpm.uper", "sdsm": "sdsm.uper"}


def _run(tmp_path, **spec):
    """A short run saving into tmp_path/w; the lists broadcast (to the OBUs' inboxes), in order."""
    run = OfflineRun(RunSpec(duration_s=2.0, **spec), save_wire=str(tmp_path / "w"))
    sent = []
    broadcast = run._broadcast

    def _broadcast(rsu, data, deliver):
        if deliver == run._obu_receive:
            sent.append((rsu.cfg.id, data))
        broadcast(rsu, data, deliver)

    run._broadcast = _broadcast
    run.execute()
    return run, sent


@pytest.mark.parametrize("wire", ["cpm", "sdsm", "v2i"])
def test_every_list_sent_is_saved_in_order_and_decodes(tmp_path, wire):
    run, sent = _run(tmp_path, wire=wire)
    rsu_id = run.rsus[0].cfg.id
    saved = sorted((tmp_path / "w" / rsu_id).iterdir())
    assert len(saved) == len(sent) >= 5  # (an SDSM: none for an empty list)
    assert [p.name for p in saved] == [f"{k:06d}.{SUFFIX[wire]}" for k in range(len(saved))]
    assert [p.read_bytes() for p in saved] == [data for _, data in sent]
    lists = [decode_list(p.read_bytes(), wire, rsu_id) for p in saved]
    assert sum(len(msg.objects) for msg in lists) > 0
    capture = [msg.header.capture_time_ns for msg in lists]
    assert capture == sorted(capture)  # send order
    assert run.wire_files[rsu_id].saved == len(saved) and run.wire_files[rsu_id].failed == 0


def test_signed_run_saves_the_unsigned_bytes(tmp_path):
    run, sent = _run(tmp_path, wire="cpm", security="strict")
    saved = sorted((tmp_path / "w" / run.rsus[0].cfg.id).iterdir())
    assert len(saved) == len(sent) > 0
    assert all(p.read_bytes() == unwrap(data) != data for p, (_, data) in zip(saved, sent))


def test_saving_changes_nothing_of_the_report(tmp_path):
    spec = RunSpec(duration_s=2.0)
    plain = OfflineRun(spec)
    plain.execute()
    saving = OfflineRun(spec, save_wire=str(tmp_path / "w"))
    saving.execute()
    assert json.dumps(plain.report(), sort_keys=True) == json.dumps(saving.report(), sort_keys=True)


def test_cli_saves_and_refuses_a_folder_it_cannot_write(tmp_path, capsys):
    assert main(["eval", "--duration", "1", "--wire", "sdsm", "--save-wire", str(tmp_path / "w")]) == 0
    assert "lists saved in" in capsys.readouterr().err
    (folder,) = (tmp_path / "w").iterdir()  # the scenario's one RSU
    assert [p.name for p in sorted(folder.iterdir())][:2] == ["000000.sdsm.uper", "000001.sdsm.uper"]
    (tmp_path / "file").write_text("")
    assert main(["eval", "--duration", "1", "--save-wire", str(tmp_path / "file" / "w")]) == 2
    assert "--save-wire" in capsys.readouterr().err
    assert main(["eval", "--table", "seeds", "--save-wire", str(tmp_path / "w")]) == 2
