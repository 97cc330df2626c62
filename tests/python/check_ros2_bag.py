"""Reads a ROS 2 bag that our tools wrote with two independent clients and prints what they saw
as JSON: `rosbags` (the bag directory or a bare .mcap, decoding against the schemas in the bag)
and Foxglove's `mcap-ros2-support` decoder (every message of every .mcap file).

    check_ros2_bag.py BAG_DIR_OR_MCAP
"""
import json
import sys
from pathlib import Path

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

path = Path(sys.argv[1])
report = {"rosbags": {}, "mcap_ros2": {}, "images": [], "qos": {}, "profile": None}
with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
    for connection in reader.connections:
        report["qos"][connection.topic] = [str(q.durability) for q in connection.ext.offered_qos_profiles]
    for connection, log_time, raw in reader.messages(connections=reader.connections):
        message = reader.deserialize(raw, connection.msgtype)
        entry = report["rosbags"].setdefault(connection.topic, {"type": connection.msgtype, "count": 0})
        entry["count"] += 1
        if connection.msgtype == "sensor_msgs/msg/Image":
            assert message.data.size == message.height * message.step, connection.topic
            stamp = message.header.stamp.sec * 10**9 + message.header.stamp.nanosec
            report["images"].append({"topic": connection.topic, "encoding": message.encoding,
                                     "frame_id": message.header.frame_id, "stamp": stamp, "log_time": log_time,
                                     "width": message.width, "height": message.height,
                                     "first_bytes": message.data[:6].tolist()})
        if connection.msgtype == "sensor_msgs/msg/CameraInfo":
            report["camera_info_k"] = message.k.tolist()
        if connection.topic == "/tf_static":
            report["static_frames"] = sorted(
                f"{t.header.frame_id}->{t.child_frame_id}" for t in message.transforms)
files = [path] if path.is_file() else sorted(path.glob("*.mcap"))
for file in files:
    with open(file, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        report["profile"] = reader.get_header().profile
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            entry = report["mcap_ros2"].setdefault(channel.topic, {"type": schema.name, "count": 0})
            entry["count"] += 1
print(json.dumps(report))
