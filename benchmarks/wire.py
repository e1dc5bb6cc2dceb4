"""Bytes and times of an RSU object list on each wire, and today's codec as the baseline, in one run.

    python benchmarks/wire.py                    # N = 10, 50, 100, 200, 1000
    python benchmarks/wire.py --n 200 --repeat 9  # ends with one line per standard wire at 200 objects

Every codec is driven through one interface, ``encode(header, objects) -> bytes`` and
``decode(bytes) -> (header, objects)``, ``objects`` an ``ObjectArray`` in and whatever the codec
decodes to out (what the OBU then fuses: an ``ObjectArray`` for v2i):

- ``v2i``: ``states_from_objects`` + ``ObjectList`` + ``schemas.codec.encode``; decode is
  ``schemas.codec.decode`` + ``objects_from_states`` (the OBU's receive path);
- ``v3``: the same with today's codec before schema 4 (``tests/unit/legacy_codec.py``: fixed-width
  columns, one pydantic model per object) and its per-object ``v2i.fusion.wire`` conversions (copied
  below), the baseline of the ratios;
- ``cpm`` / ``sdsm``: ``schemas.cpm`` / ``schemas.sdsm`` (UPER, at most 255 objects).

Objects: a synthetic RSU track list (positions within +-150 m, tracked velocities and
accelerations, correlated position and velocity covariances, ages up to 2 s). Bytes are given
at two resolutions: ``native`` (the tracker's values on the v2i grid) and ``CPM res`` (the same
objects after a CPM round trip, i.e. exactly what a CPM can say: dimensions 0.1 m, acceleration
0.1 m/s^2, yaw rate 1 deg/s, position/speed standard deviations 0.01 m / 0.01 m/s via 95 %
confidence, correlations 1 %, confidence 1/15; see ``schemas.cpm``). Per object = (bytes(N) -
bytes(0)) / N, so the per-message column layout is included; header = bytes(0) (SDSM has no
empty message: per object = (bytes(N) - bytes(1)) / (N - 1)). Times: median of
``--repeat`` runs of a loop sized to ~20 ms, microseconds per message. The v2i codec packs its
rows with the compiled loops, as the services do once they load their kernels (``schemas.bitpack``);
``--numpy-bits`` times it as a process that never loads them (an outside publisher) runs it.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "unit"))
import legacy_codec as v3  # noqa: E402

from v2i.core.jit import load_kernels  # noqa: E402
from v2i.core.objects import ObjectArray  # noqa: E402
from v2i.fusion.wire import objects_from_states, states_from_objects  # noqa: E402
from schemas.codec import decode, encode  # noqa: E402
from schemas.messages import ObjectList, ObjectListHeader, ObjectState  # noqa: E402

T0 = 1_700_000_000 * 10**9
HEADER = ObjectListHeader(rsu_id="rsu-0", seq=123_456, capture_time_ns=T0, publish_time_ns=T0 + 95_000_000)


# ---------------------------------------------------------------- today's conversions (schema 3)


def v3_states(objs: ObjectArray) -> tuple[ObjectState, ...]:
    """v2i.fusion.wire.states_from_objects before schema 4: one model per object."""
    out = []
    for i in range(len(objs)):
        out.append(ObjectState(
            id=int(objs.ids[i]), cls=int(objs.cls[i]), x=float(objs.xy[i, 0]), y=float(objs.xy[i, 1]),
            z=float(objs.z[i]), length=float(objs.lwh[i, 0]), width=float(objs.lwh[i, 1]),
            height=float(objs.lwh[i, 2]), yaw=float(objs.yaw[i]), vx=float(objs.vxy[i, 0]),
            vy=float(objs.vxy[i, 1]), ax=float(objs.axy[i, 0]), ay=float(objs.axy[i, 1]),
            yaw_rate=float(objs.yaw_rate[i]), cov_xx=float(objs.cov_xy[i, 0, 0]),
            cov_xy=float(objs.cov_xy[i, 0, 1]), cov_yy=float(objs.cov_xy[i, 1, 1]),
            cov_vxx=float(objs.cov_vxy[i, 0, 0]), cov_vxy=float(objs.cov_vxy[i, 0, 1]),
            cov_vyy=float(objs.cov_vxy[i, 1, 1]),
            confidence=float(np.clip(objs.confidence[i], 0.0, 1.0)), age_s=float(max(objs.age_s[i], 0.0))))
    return tuple(out)


_NAMES = ("id", "cls", "x", "y", "z", "length", "width", "height", "yaw", "vx", "vy", "ax", "ay", "yaw_rate",
          "cov_xx", "cov_xy", "cov_yy", "cov_vxx", "cov_vxy", "cov_vyy", "confidence", "age_s")


def v3_objects(states) -> ObjectArray:
    """v2i.fusion.wire.objects_from_states before schema 4: attribute reads per object."""
    if not states:
        return ObjectArray.empty()
    c = {k: np.array([getattr(s, k) for s in states]) for k in _NAMES}

    def sym(a, b, d):
        return np.stack([np.stack([c[a], c[b]], -1), np.stack([c[b], c[d]], -1)], -2)

    return ObjectArray(ids=c["id"].astype(np.int64), cls=c["cls"].astype(np.int64), xy=np.column_stack([c["x"], c["y"]]),
                       z=c["z"], lwh=np.column_stack([c["length"], c["width"], c["height"]]), yaw=c["yaw"],
                       vxy=np.column_stack([c["vx"], c["vy"]]), axy=np.column_stack([c["ax"], c["ay"]]),
                       yaw_rate=c["yaw_rate"], cov_xy=sym("cov_xx", "cov_xy", "cov_yy"),
                       cov_vxy=sym("cov_vxx", "cov_vxy", "cov_vyy"), confidence=c["confidence"], age_s=c["age_s"],
                       sources=np.zeros(len(states), np.int64))


# ---------------------------------------------------------------- codecs: encode(header, objects), decode(bytes)


def v2i_codec():
    return (lambda h, o: encode(ObjectList(header=h, objects=states_from_objects(o))),
            lambda b: (lambda m: (m.header, objects_from_states(m.objects)))(decode(b, ObjectList)))


def v3_codec():
    return (lambda h, o: v3.encode(v3.ObjectList(header=h, objects=v3_states(o))),
            lambda b: (lambda m: (m.header, v3_objects(m.objects)))(v3.decode(b, v3.ObjectList)))


def standard_codec(name: str):
    try:
        mod = __import__(f"schemas.{name}", fromlist=["encode", "decode"])
    except ImportError:
        return None
    return mod.encode, mod.decode


CODECS: dict[str, Callable] = {"v2i": v2i_codec, "v3": v3_codec, "cpm": lambda: standard_codec("cpm"),
                               "sdsm": lambda: standard_codec("sdsm")}
LIMIT = {"cpm": 255, "sdsm": 255}


# ---------------------------------------------------------------- objects


def rsu_tracks(n: int, rng: np.random.Generator, rich: bool = True) -> ObjectArray:
    """N tracked road users around an intersection (map frame). ``rich``: with accelerations, yaw
    rates and correlated covariances; otherwise those are zero (what a CPM then leaves out: the
    "typical object" of issue 15's ~28 B CPM figure)."""
    cls = rng.choice([1, 1, 1, 2, 3, 5, 6], n)
    dims = {1: (4.5, 1.8, 1.5), 2: (5.2, 2.0, 2.0), 3: (9.0, 2.5, 3.2), 5: (0.6, 0.6, 1.7), 6: (1.8, 0.6, 1.7)}
    lwh = np.array([dims[c] for c in cls]) * rng.uniform(0.9, 1.1, (n, 3))
    speed = np.where(cls >= 5, rng.uniform(0, 2, n), rng.uniform(0, 15, n))
    yaw = rng.uniform(-np.pi, np.pi, n)
    vxy = speed[:, None] * np.column_stack([np.cos(yaw), np.sin(yaw)])

    def cov(sigma_lo, sigma_hi):
        s = rng.uniform(sigma_lo, sigma_hi, (n, 2))
        rho = rng.uniform(-0.3, 0.3, n) * rich
        c = np.empty((n, 2, 2))
        c[:, 0, 0], c[:, 1, 1] = s[:, 0] ** 2, s[:, 1] ** 2
        c[:, 0, 1] = c[:, 1, 0] = rho * s[:, 0] * s[:, 1]
        return c

    return ObjectArray(ids=rng.permutation(n) + 1000, cls=cls, xy=rng.uniform(-150, 150, (n, 2)), z=np.zeros(n),
                       lwh=lwh, yaw=yaw, vxy=vxy, axy=rng.uniform(-2, 2, (n, 2)) * rich,
                       yaw_rate=rng.uniform(-0.3, 0.3, n) * rich,
                       cov_xy=cov(0.1, 0.5), cov_vxy=cov(0.2, 1.0), confidence=rng.uniform(0.5, 1.0, n),
                       age_s=rng.uniform(0, 2.0, n))


def at_cpm_resolution(objs: ObjectArray) -> ObjectArray | None:
    """The objects as a CPM carries them (a CPM round trip, 200 at a time); None without schemas.cpm."""
    codec = standard_codec("cpm")
    if codec is None:
        return None
    parts = []
    for start in range(0, len(objs), 200):
        part = objs.take(np.arange(start, min(start + 200, len(objs))))
        _, cols = codec[1](codec[0](HEADER, part))
        back = states_from_objects(part)  # the v2i columns, then overwritten by what the CPM said
        table = np.column_stack([cols[k] for k in back.names])
        table[:, 0] = part.ids  # the CPM's ids are 16 bit; keep the track ids
        parts.append(objects_from_states(type(back).from_values(table)))
    return ObjectArray.concat(parts)


# ---------------------------------------------------------------- measuring


def per_call_us(fn: Callable[[], object], repeat: int) -> float:
    """Median over ``repeat`` runs of a loop sized to ~20 ms: microseconds per call."""
    t = time.perf_counter()
    fn()
    loops = max(1, int(0.02 / max(time.perf_counter() - t, 1e-7)))
    runs = []
    for _ in range(repeat):
        t = time.perf_counter()
        for _ in range(loops):
            fn()
        runs.append((time.perf_counter() - t) / loops * 1e6)
    return statistics.median(runs)


def header_bytes(enc: Callable) -> int | str:
    """Bytes of a list with no object ("n/a" for an encoding that has none: SDSM carries 1..255)."""
    try:
        return len(enc(HEADER, ObjectArray.empty()))
    except ValueError:
        return "n/a"


def size_table(ns: list[int], objs_by_n: dict, cpm_res: dict, codecs: dict) -> None:
    print("bytes: header = message with 0 objects; per object = (bytes(N) - bytes(0)) / N")
    cols = [(name, res) for name in codecs for res in ("native", "CPM res")]
    print(f"{'N':>6} " + " ".join(f"{name + ' ' + res:>16}" for name, res in cols))
    heads = {name: header_bytes(enc) for name, (enc, _) in codecs.items()}
    print(f"{'header':>6} " + " ".join(f"{heads[name]:>16}" for name, _ in cols))
    for n in ns:
        cells = []
        for name, res in cols:
            objs = objs_by_n[n] if res == "native" else cpm_res.get(n)
            if objs is None or n > LIMIT.get(name, 10**9):
                cells.append(f"{'n/a':>16}")
                continue
            size = len(codecs[name][0](HEADER, objs))
            if heads[name] == "n/a":  # no empty message: per object after the first
                one = len(codecs[name][0](HEADER, objs.take(0)))
                cells.append(f"{(size - one) / max(n - 1, 1):>16.1f}")
            else:
                cells.append(f"{(size - heads[name]) / n:>16.1f}")
        print(f"{n:>6} " + " ".join(cells))


def time_table(ns: list[int], objs_by_n: dict, codecs: dict, repeat: int) -> None:
    print(f"\ntimes: us per message, median of {repeat} (encode: ObjectArray -> bytes; decode: bytes -> objects); "
          "ratio = v3 / v2i")
    names = list(codecs)
    print(f"{'N':>6} " + " ".join(f"{n + ' enc':>11} {n + ' dec':>11}" for n in names)
          + f" {'enc ratio':>10} {'dec ratio':>10} {'codec-only enc':>15} {'codec-only dec':>15}")
    for n in ns:
        objs, row, t = objs_by_n[n], [], {}
        for name in names:
            enc, dec = codecs[name]
            if n > LIMIT.get(name, 10**9):
                row.append(f"{'n/a':>11} {'n/a':>11}")
                continue
            data = enc(HEADER, objs)
            t[name] = (per_call_us(lambda: enc(HEADER, objs), repeat), per_call_us(lambda: dec(data), repeat))
            row.append(f"{t[name][0]:>11.1f} {t[name][1]:>11.1f}")
        msg = ObjectList(header=HEADER, objects=states_from_objects(objs))
        data = encode(msg)
        cached = msg.objects.__dict__  # the columns keep their packed section (wire_section): pack it afresh each call

        def encode_afresh():
            cached.pop("wire_section", None)
            return encode(msg)

        only = (per_call_us(encode_afresh, repeat), per_call_us(lambda: decode(data, ObjectList), repeat))
        ratio = f"{t['v3'][0] / t['v2i'][0]:>10.1f} {t['v3'][1] / t['v2i'][1]:>10.1f}"
        print(f"{n:>6} " + " ".join(row) + f" {ratio} {only[0]:>15.1f} {only[1]:>15.1f}")


def standard_summary(codecs: dict, seed: int, repeat: int, n: int = 200) -> None:
    """One line per standard wire: bytes per object (typical and rich, native resolution) and the
    encode / decode time of one message of ``n`` rich objects (issue 30's acceptance figures)."""
    print(f"\nstandard wires at {n} objects: bytes per object = (bytes({n}) - header) / {n}; ms per message")
    for name in ("cpm", "sdsm"):
        if name not in codecs:
            continue
        enc, dec = codecs[name]
        head = header_bytes(enc)
        per = []
        for rich in (False, True):
            objs = rsu_tracks(n, np.random.default_rng(seed), rich)
            base = len(enc(HEADER, objs.take(0))) if head == "n/a" else head
            per.append((len(enc(HEADER, objs)) - base) / (n - 1 if head == "n/a" else n))
        data = enc(HEADER, objs)
        head_text = "none" if head == "n/a" else f"{head} B"
        t_enc, t_dec = per_call_us(lambda: enc(HEADER, objs), repeat), per_call_us(lambda: dec(data), repeat)
        print(f"{name}: {per[0]:.1f} B/object typical, {per[1]:.1f} B/object rich, header {head_text}; "
              f"{n} objects: encode {t_enc / 1e3:.2f} ms, decode {t_dec / 1e3:.2f} ms ({len(data)} B)")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", default="10,50,100,200,1000", help="object counts, comma-separated")
    ap.add_argument("--repeat", type=int, default=7, help="timed runs per cell (median)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--numpy-bits", action="store_true", help="v2i rows packed by numpy, not the compiled loops")
    args = ap.parse_args(argv)
    if not args.numpy_bits:
        load_kernels(("schemas.bit_rows",))
    ns = [int(v) for v in args.n.split(",")]
    codecs = {name: c for name, make in CODECS.items() if (c := make()) is not None}
    rng = np.random.default_rng(args.seed)
    for rich in (False, True):
        objs_by_n = {n: rsu_tracks(n, rng, rich) for n in ns}
        cpm_res = {n: at_cpm_resolution(o) for n, o in objs_by_n.items()}
        print(f"\n=== {'rich objects (accelerations, yaw rates, correlated covariances)' if rich else 'typical objects (no acceleration, yaw rate or correlation)'}")
        size_table(ns, objs_by_n, {n: o for n, o in cpm_res.items() if o is not None}, codecs)
    time_table(ns, objs_by_n, codecs, args.repeat)
    standard_summary(codecs, args.seed, args.repeat)


if __name__ == "__main__":
    main()
