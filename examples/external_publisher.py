"""Feed a vehicle's OBU with your own perception: its pose and its detections, at 10 Hz; and, with
--rsu-connect, a roadside unit with its camera's detections of the same car, at 5 Hz.

Start the OBU on its inputs, then this publisher (both on this host: the stamps are its clock):

    v2i obu --source zenoh --listen tcp/127.0.0.1:7448
    python examples/external_publisher.py --connect tcp/127.0.0.1:7448

The OBU fuses what arrives (with any RSU it hears) and publishes on v2x/obu/ego/objects.
The whole site, with no scenario (examples/site.yaml: this RSU and this vehicle):

    v2i rsu --site examples/site.yaml --source zenoh --listen tcp/127.0.0.1:7447
    v2i obu --site examples/site.yaml --source zenoh --listen tcp/127.0.0.1:7448 --connect tcp/127.0.0.1:7447
    python examples/external_publisher.py --connect tcp/127.0.0.1:7448 --rsu-connect tcp/127.0.0.1:7447

Replace ``detect()``, ``localise()`` and ``observe()`` with your sensors.
"""

import argparse
import time

import zenoh

from schemas import keys
from schemas.codec import encode
from schemas.messages import ObjectState
from schemas.sensor_messages import LocalizationPose, SensorHeader, SensorObjects

CAR = 1  # schemas.classes.ObjectClass.CAR


def localise(t_s: float) -> LocalizationPose:
    """The vehicle driving east at 10 m/s along y = 0 (map frame), 5 cm / 0.3 deg uncertain."""
    return LocalizationPose(vehicle_id=ARGS.vehicle_id, seq=round(t_s * 10), t_ns=time.time_ns(), x=10.0 * t_s,
                            y=0.0, yaw=0.0, vx=10.0, cov_xx=0.0025, cov_yy=0.0025, cov_yawyaw=2.5e-5)


def detect() -> list[ObjectState]:
    """One car 20 m ahead, 3.5 m to the left, keeping pace (base_link: x forward, y left; velocity over
    ground, in base_link axes)."""
    return [ObjectState(id=0, cls=CAR, x=20.0, y=3.5, length=4.5, width=1.8, vx=10.0, cov_xx=0.04, cov_yy=0.04,
                        cov_vxx=0.09, cov_vyy=0.09)]


def observe(t_s: float) -> list[ObjectState]:
    """The roadside camera's view of the same car (map frame: x east, y north; a monocular camera
    measures no velocity: its variance says "not measured")."""
    return [ObjectState(id=0, cls=CAR, x=10.0 * t_s + 20.0, y=3.5, length=4.5, width=1.8, cov_xx=0.25,
                        cov_yy=0.25)]


def sensor_objects(sensor_id: str, sensor: str, seq: int, frame_id: str, capture_ns: int, objects) -> bytes:
    header = SensorHeader(sensor_id=sensor_id, sensor=sensor, seq=seq, frame_id=frame_id,
                          capture_time_ns=capture_ns, ready_time_ns=time.time_ns())
    return encode(SensorObjects(header=header, objects=objects))


def session_to(endpoint: str) -> zenoh.Session:
    conf = zenoh.Config()  # explicit endpoints, no discovery (as every v2i service)
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", f'["{endpoint}"]')
    return zenoh.open(conf)


def main() -> None:
    with session_to(ARGS.connect) as session:
        pose_pub = session.declare_publisher(keys.sensor_vehicle_pose(ARGS.vehicle_id))
        objects_pub = session.declare_publisher(keys.sensor_vehicle_objects(ARGS.vehicle_id))
        rsu = session_to(ARGS.rsu_connect) if ARGS.rsu_connect else None
        camera_pub = rsu.declare_publisher(keys.sensor_rsu_objects(ARGS.rsu_id)) if rsu else None
        t0 = time.monotonic()
        for seq in range(round(ARGS.duration * 10)):
            time.sleep(max(t0 + seq / 10 - time.monotonic(), 0.0))  # 10 Hz
            capture_ns = time.time_ns()
            pose_pub.put(encode(localise(seq / 10)))
            # your detector: capture -> detections in base_link
            objects_pub.put(sensor_objects(ARGS.vehicle_id, "lidar", seq, "base_link", capture_ns, detect()))
            if camera_pub is not None and seq % 2 == 0:  # the roadside camera at 5 Hz, in map
                camera_pub.put(sensor_objects(ARGS.rsu_id, "camera", seq // 2, "map", capture_ns, observe(seq / 10)))
        for publisher in (pose_pub, objects_pub, camera_pub):
            if publisher is not None:
                publisher.undeclare()
        if rsu is not None:
            rsu.close()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--connect", default="tcp/127.0.0.1:7448", help="the OBU's listen endpoint")
    parser.add_argument("--vehicle-id", default="ego")
    parser.add_argument("--rsu-connect", help="also feed a roadside unit (v2i rsu --source zenoh) on this endpoint")
    parser.add_argument("--rsu-id", default="rsu1")
    parser.add_argument("--duration", type=float, default=10.0, help="seconds to publish")
    ARGS = parser.parse_args()
    main()
