"""Runs inside a network namespace of its own (started by test_ros2_cyclone.py through `unshare
--net`): brings `lo` up with multicast, starts `moma ros2` and `moma ros2-replay`, and subscribes
to the node's `depth` and `grasps_json` with Eclipse Cyclone DDS, an independent DDS
implementation, using the ROS 2 type names. Writes what it received under OUT.

Usage: python ros2_cyclone_driver.py MOMA_BIN SET PREDS CALIB OUT
"""

import json
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np

DOMAIN = 21


def setup_loopback():
    for args in (["link", "set", "lo", "up"], ["link", "set", "lo", "multicast", "on"],
                 ["route", "add", "224.0.0.0/4", "dev", "lo"]):
        subprocess.run(["ip", *args], check=True)
    links = subprocess.run(["ip", "-o", "link"], check=True, capture_output=True, text=True).stdout
    assert len(links.strip().splitlines()) == 1, f"only lo in the namespace: {links}"


def main():
    moma, set_dir, preds, calib, out = sys.argv[1:6]
    setup_loopback()
    os.environ["CYCLONEDDS_URI"] = (
        "<CycloneDDS><Domain id='any'><General><Interfaces>"
        "<NetworkInterface name='lo' multicast='true'/></Interfaces>"
        "<AllowMulticast>true</AllowMulticast></General></Domain></CycloneDDS>")

    from cyclonedds.core import Policy, Qos
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.idl import IdlStruct
    from cyclonedds.idl.annotations import final
    from cyclonedds.idl.types import int32, sequence, uint8, uint32
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic

    # The ROS 2 message definitions, as rosidl generates them for DDS (final, XCDR1).
    @final
    @dataclass
    class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
        sec: int32
        nanosec: uint32

    @final
    @dataclass
    class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
        stamp: Time
        frame_id: str

    @final
    @dataclass
    class Image(IdlStruct, typename="sensor_msgs::msg::dds_::Image_"):
        header: Header
        height: uint32
        width: uint32
        encoding: str
        is_bigendian: uint8
        step: uint32
        data: sequence[uint8]

    @final
    @dataclass
    class String(IdlStruct, typename="std_msgs::msg::dds_::String_"):
        data: str

    node = subprocess.Popen([moma, "ros2", "--calib", calib, "--input", "prediction",
                             "--gripper", "suction", "--top", "3", "--localhost-only",
                             "--domain-id", str(DOMAIN), "--max-seconds", "90"])
    dp = DomainParticipant(DOMAIN)
    qos = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(4))
    depth_reader = DataReader(dp, Topic(dp, "rt/depth", Image), qos=qos)
    json_reader = DataReader(dp, Topic(dp, "rt/grasps_json", String), qos=qos)

    replay = subprocess.Popen([moma, "ros2-replay", "--set", set_dir, "--pred", preds,
                               "--rate", "2", "--loop", "--max-frames", "60", "--warmup-s", "2",
                               "--localhost-only", "--domain-id", str(DOMAIN)],
                              stdout=subprocess.PIPE, text=True)
    stamps = {}

    def read_stamps():
        for line in replay.stdout:
            parts = line.split()
            if len(parts) == 4 and parts[0] == "frame" and parts[2] == "stamp":
                sec, ns = parts[3].split(".")
                stamps[(int(sec), int(ns))] = parts[1]

    threading.Thread(target=read_stamps, daemon=True).start()
    n_frames = len(os.listdir(os.path.join(set_dir, "frames")))
    received, grasps = {}, []
    deadline = time.time() + 80
    try:
        while time.time() < deadline and (len(received) < n_frames or not grasps):
            for img in depth_reader.take(N=8):
                key = (img.header.stamp.sec, img.header.stamp.nanosec)
                name = stamps.get(key)
                if name is None:
                    time.sleep(0.2)
                    name = stamps.get(key)
                assert name is not None, f"depth with a stamp the replay never sent: {key}"
                assert img.encoding == "32FC1" and img.is_bigendian == 0
                arr = np.frombuffer(bytes(img.data), dtype="<f4").reshape(img.height, img.width)
                if name not in received:
                    np.save(os.path.join(out, f"{name}.received.npy"), arr)
                received[name] = received.get(name, 0) + 1
            for s in json_reader.take(N=8):
                grasps.append(json.loads(s.data))
            time.sleep(0.01)
    finally:
        for p in (replay, node):
            p.kill()
            p.wait()
    with open(os.path.join(out, "summary.json"), "w") as f:
        json.dump({"received": received, "grasps": grasps[:3], "n_grasp_messages": len(grasps)}, f)


if __name__ == "__main__":
    main()
