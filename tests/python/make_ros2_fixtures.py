"""Writes the golden CDR payloads of tests/corpus/ros2 with the `rosbags` library (not our code).

Run once (the files are committed): .venv/bin/python tests/python/make_ros2_fixtures.py
Each file is one message as it sits in a bag: the 4-byte encapsulation header, then the CDR.
The values are the ones `ros2::msg` tests expect (tests/e2e/ros2_cdr.rs).
"""
from pathlib import Path

import numpy as np
from rosbags.typesys import Stores, get_typestore

ts = get_typestore(Stores.ROS2_JAZZY)
T = ts.types
OUT = Path(__file__).resolve().parent.parent / "corpus" / "ros2"
OUT.mkdir(parents=True, exist_ok=True)


def hdr(sec, nanosec, frame):
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame)


def roi(x, y, h, w, rect):
    return T["sensor_msgs/msg/RegionOfInterest"](x_offset=x, y_offset=y, height=h, width=w, do_rectify=rect)


def image(encoding, data, width, height, step):
    return T["sensor_msgs/msg/Image"](header=hdr(1700000000, 123456789, "camera_color_optical_frame"), height=height,
                                      width=width, encoding=encoding, is_bigendian=0, step=step, data=data)


def tf(sec, parent, child, t, q):
    return T["geometry_msgs/msg/TransformStamped"](
        header=hdr(sec, 500, parent), child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=t[0], y=t[1], z=t[2]),
            rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])))


rgb = np.arange(2 * 3 * 3, dtype=np.uint8)
depth = np.array([0.5, 1.25, 0.0, 2.0], dtype=np.float32)
camera_info = T["sensor_msgs/msg/CameraInfo"](
    header=hdr(1700000000, 123456789, "camera_color_optical_frame"), height=480, width=640,
    distortion_model="plumb_bob", d=np.array([0.1, -0.2, 0.001, 0.002, 0.0]),
    k=np.array([600.0, 0, 320.5, 0, 601.0, 240.25, 0, 0, 1]), r=np.eye(3).ravel(),
    p=np.array([600.0, 0, 320.5, 0, 0, 601.0, 240.25, 0, 0, 0, 1, 0]), binning_x=0, binning_y=0,
    roi=roi(0, 0, 0, 0, False))
messages = {
    "image_rgb8": (image("rgb8", rgb, 3, 2, 9), "sensor_msgs/msg/Image"),
    "image_32fc1": (image("32FC1", depth.view(np.uint8), 2, 2, 8), "sensor_msgs/msg/Image"),
    "compressed_image": (T["sensor_msgs/msg/CompressedImage"](
        header=hdr(1700000000, 123456789, "camera_color_optical_frame"), format="rgb8; jpeg compressed bgr8",
        data=np.array([0xFF, 0xD8, 0xFF, 0xD9], dtype=np.uint8)), "sensor_msgs/msg/CompressedImage"),
    "camera_info": (camera_info, "sensor_msgs/msg/CameraInfo"),
    "tf": (T["tf2_msgs/msg/TFMessage"](transforms=[
        tf(1700000000, "base_link", "tool0", (0.5, 0.0, 0.4), (0.0, 0.0, 0.0, 1.0)),
        tf(1700000000, "tool0", "camera_color_optical_frame", (0.0, 0.05, 0.1), (-0.5, 0.5, -0.5, 0.5))]),
           "tf2_msgs/msg/TFMessage"),
    "joint_state": (T["sensor_msgs/msg/JointState"](
        header=hdr(1700000000, 8000000, ""), name=["elbow_joint", "shoulder_lift_joint", "shoulder_pan_joint"],
        position=np.array([1.5, -1.25, 0.5]), velocity=np.array([0.0, 0.01, 0.0]), effort=np.array([])),
                    "sensor_msgs/msg/JointState"),
    "string": (T["std_msgs/msg/String"](data='{"set_index": 0}'), "std_msgs/msg/String"),
    "disparity_image": (T["stereo_msgs/msg/DisparityImage"](
        header=hdr(1700000000, 123456789, "camera_color_optical_frame"), image=image("32FC1", depth.view(np.uint8), 2, 2, 8),
        f=600.0, t=0.02, valid_window=roi(0, 0, 2, 2, False), min_disparity=0.0, max_disparity=64.0, delta_d=0.125),
                        "stereo_msgs/msg/DisparityImage"),
    "point_cloud2": (T["sensor_msgs/msg/PointCloud2"](
        header=hdr(1700000000, 123456789, "camera_color_optical_frame"), height=1, width=2,
        fields=[T["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")],
        is_bigendian=False, point_step=12, row_step=24,
        data=np.array([0.1, 0.2, 1.0, -0.1, 0.0, 2.0], dtype=np.float32).view(np.uint8), is_dense=True),
                     "sensor_msgs/msg/PointCloud2"),
}
for name, (message, typename) in messages.items():
    (OUT / f"{name}.cdr").write_bytes(bytes(ts.serialize_cdr(message, typename)))
# The same camera info in big-endian CDR (rosbags writes it with little_endian=False).
(OUT / "camera_info_be.cdr").write_bytes(bytes(ts.serialize_cdr(camera_info, "sensor_msgs/msg/CameraInfo", little_endian=False)))
print(f"wrote {len(messages) + 1} payloads to {OUT}")
