"""Issue 32's acceptance at the command line: /dev/zero (behind a symlink), a FIFO and a 100 MB
sparse file as ``--config``, as the CA certificate in ``--pki`` (the RSU's own certificate for
``v2i rsu``) and as ``--site``: exit 2 within seconds, one stderr line naming the file and its
limit, no traceback, memory bounded."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time

import pytest

from v2i.core.files import MiB
from v2i.security.site import write_site

KINDS = ("zero", "fifo", "big")
FINDING = {"zero": "a character device", "fifo": "a FIFO", "big": f"{100 * MiB} bytes"}
WALL_LIMIT_S = 20.0  # ~1 s on an idle machine (most of it the CLI's imports); a loaded CI runner is slower
RSS_LIMIT_MB = 200  # the bound; a service's start-up is ~125 MB


def _make(path, kind: str) -> None:
    if kind == "zero":
        path.symlink_to("/dev/zero")
    elif kind == "fifo":
        os.mkfifo(path)
    else:
        with open(path, "wb") as f:
            f.truncate(100 * MiB)


@pytest.fixture(scope="module")
def site_pki(tmp_path_factory):
    return write_site(tmp_path_factory.mktemp("pki") / "pki", time.time_ns(), rsu_ids=["rsu1"], vehicle_ids=["ego"])


def _case(tmp_path, site_pki, service: str, flag: str, kind: str) -> tuple[list[str], str]:
    """The argv of one case and the error it must print."""
    if flag == "--pki":
        pki = tmp_path / "pki"
        shutil.copytree(site_pki, pki, symlinks=True)
        name = "rsu1.cert" if service == "rsu" else "ca.cert"  # what the service loads first
        (pki / name).unlink()
        _make(pki / name, kind)
        return ["--pki", str(pki), "--listen", "tcp/127.0.0.1:0"], \
            f"cannot read certificate {pki / name}: {FINDING[kind]}; a certificate must be a regular file of at most 64 KiB"
    path = tmp_path / f"{kind}.yaml"
    _make(path, kind)
    what = flag.removeprefix("--")
    extra = ["--source", "zenoh"] if flag == "--site" else []
    return [flag, str(path), *extra], \
        f"cannot read {what} {path}: {FINDING[kind]}; a {what} must be a regular file of at most 1 MiB"


# every case on the OBU; the RSU's --pki too, which reads its own key and certificate, not the CA's
# (its --config and --site go through the same readers as the OBU's)
CASES = [*(("obu", f, k) for f in ("--config", "--pki", "--site") for k in KINDS), *(("rsu", "--pki", k) for k in KINDS)]


@pytest.mark.parametrize(("service", "flag", "kind"), CASES, ids=[f"{s} {f} {k}" for s, f, k in CASES])
def test_a_hostile_file_is_one_line_at_once(tmp_path, site_pki, service, flag, kind):
    argv, expected = _case(tmp_path, site_pki, service, flag, kind)
    started = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "v2i", service, *argv], capture_output=True, text=True,
                          timeout=60, stdin=subprocess.DEVNULL, cwd=tmp_path)
    wall_s = time.monotonic() - started
    assert done.returncode == 2, done.stderr
    assert done.stderr == f"v2i {service}: {expected}\n"
    assert wall_s < WALL_LIMIT_S


def test_the_peak_memory_of_a_refusal_is_bounded(tmp_path, site_pki):
    """The worst case of the issue (/dev/zero as the OBU's CA certificate) in a child of its own:
    its peak RSS (ru_maxrss of the children, kB) stays under the issue's 200 MB."""
    argv, _ = _case(tmp_path, site_pki, "obu", "--pki", "zero")
    script = ("import resource, subprocess, sys; subprocess.run(sys.argv[1:], capture_output=True, timeout=60); "
              "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")
    done = subprocess.run([sys.executable, "-c", script, sys.executable, "-m", "v2i", "obu", *argv],
                          capture_output=True, text=True, timeout=90)
    assert int(done.stdout) / 1024 < RSS_LIMIT_MB
