"""Writes a ROS 2 bag of a multiscopic capture the way a real UR + camera system records it, with
the `rosbags` library (not our code): the test's "real robot" input.

    write_ros2_capture.py SCENE_DIR OUT_BAG --views view2@0,view1@-1,view3@1,view0@-2,view4@2
        [--baseline-mm 40] [--focal-px 1246.667] [--split] [--rest-secs 1.2] [--crop NAME]

The views are visited in the order given (stations). Between stations the arm moves for 1 s
(smoothstep) and then rests for 1.2 s (--rest-secs); the camera streams at 10 Hz throughout (stamps 3 ms past
the tenth of a second, logged 30 ms later), showing the previous station's image while it moves.
robot_state_publisher-style `/tf` at 20 Hz carries base_link -> wrist_3_link; `/tf_static` the
fixed chain wrist_3_link -> flange -> tool0 and the hand-eye result tool0 ->
camera_color_optical_frame (easy_handeye2 style); `/joint_states` at 125 Hz with the joint names
in alphabetical order (not the arm's), velocities included; CameraInfo beside every image; and a
topic of a type replay does not read (/diagnostics). `--split` writes the messages into two
storage files (as `ros2 bag record --max-bag-duration` does) with a `metadata.yaml` listing both.
Prints the camera poses of the stations as JSON (base_link frame).
"""
import argparse
import json
import math
from pathlib import Path

import numpy as np
from PIL import Image as PILImage
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

ts = get_typestore(Stores.ROS2_JAZZY)
T = ts.types
INF = QosTime(sec=2147483647, nsec=4294967295)
LATCHED = Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL, INF, INF,
              QosLiveliness.AUTOMATIC, INF, False)
CAMERA_FRAME = "camera_color_optical_frame"
JOINTS = ["elbow_joint", "shoulder_lift_joint", "shoulder_pan_joint", "wrist_1_joint", "wrist_2_joint",
          "wrist_3_joint"]


def quat_mul(a, b):
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz)


def quat_rotate(q, v):
    x, y, z, w = q
    qv = (v[0], v[1], v[2], 0.0)
    r = quat_mul(quat_mul(q, qv), (-x, -y, -z, w))
    return np.array(r[:3])


def quat_inv(q):
    return (-q[0], -q[1], -q[2], q[3])


def compose(a, b):
    """(t, q) of a * b."""
    return a[0] + quat_rotate(a[1], b[0]), quat_mul(a[1], b[1])


def inverse(a):
    qi = quat_inv(a[1])
    return -quat_rotate(qi, a[0]), qi


def axis_angle(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    s = math.sin(angle / 2)
    return (axis[0] * s, axis[1] * s, axis[2] * s, math.cos(angle / 2))


def hdr(ns, frame):
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                    frame_id=frame)


def tf(ns, parent, child, pose):
    t, q = pose
    return T["geometry_msgs/msg/TransformStamped"](
        header=hdr(ns, parent), child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=float(t[0]), y=float(t[1]), z=float(t[2])),
            rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])))


def camera_info(header, width, height, focal_px):
    """An ideal pinhole's CameraInfo: f, a centred principal point, no distortion."""
    cx, cy = (width - 1) / 2, (height - 1) / 2
    return T["sensor_msgs/msg/CameraInfo"](
        header=header, height=height, width=width, distortion_model="plumb_bob", d=np.zeros(5),
        k=np.array([focal_px, 0, cx, 0, focal_px, cy, 0, 0, 1]), r=np.eye(3).ravel(),
        p=np.array([focal_px, 0, cx, 0, 0, focal_px, cy, 0, 0, 0, 1, 0]), binning_x=0, binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("scene", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--views", required=True)
    parser.add_argument("--baseline-mm", type=float, default=40.0)
    parser.add_argument("--focal-px", type=float, default=3740 / 3)  # Middlebury 2006 third size
    parser.add_argument("--split", action="store_true")
    parser.add_argument("--rest-secs", type=float, default=1.2, help="how long the arm rests at each station")
    parser.add_argument("--crop", help="NAME: that view's images lose their last 10 columns (a bad bag)")
    parser.add_argument("--realsense", action="store_true",
                        help="also stream what a RealSense adds: infrared (mono8, its own optical frame 15 mm "
                             "beside the colour one, 5 ms later), depth (16UC1) and a yuv422 colour stream")
    args = parser.parse_args()
    views = []
    for item in args.views.split(","):
        name, offset = item.rsplit("@", 1)
        rgb = np.asarray(PILImage.open(args.scene / (name if "." in name else name + ".png")).convert("RGB"))
        if name == args.crop:
            rgb = np.ascontiguousarray(rgb[:, :-10])
        views.append((rgb, float(offset)))
    height, width = views[0][0].shape[:2]
    baseline = args.baseline_mm / 1000.0
    # The reference camera looks down and forward at the scene; views move along its own x axis.
    camera_rotation = quat_mul(axis_angle((0, 0, 1), 0.3), axis_angle((1, 0, 0), math.pi * 0.8))
    reference_position = np.array([0.6, 0.1, 0.7])
    hand_eye = (np.array([0.01, -0.04, 0.08]), axis_angle((0.2, 0.1, 1.0), 0.9))  # tool0 <- camera
    wrist_from_tool0 = (np.array([0.0, 0.0, 0.0823]), axis_angle((0, 0, 1), -math.pi / 2))  # via flange

    def camera_pose(offset):
        return reference_position + quat_rotate(camera_rotation, (offset * baseline, 0.0, 0.0)), camera_rotation

    def wrist_pose(camera):
        # base <- wrist3 = base <- camera * (wrist3 <- camera)^-1
        wrist_from_camera = compose(wrist_from_tool0, hand_eye)
        return compose(camera, inverse(wrist_from_camera))

    # Timeline: rest 1.2 s at each station, move 1 s between stations.
    rest, move = int(args.rest_secs * 1e9), 1_000_000_000
    start = 1_700_000_000_000_000_000
    segments = []  # (t0, t1, from_offset, to_offset, station index or None)
    t = start
    for i, (_, offset) in enumerate(views):
        if i > 0:
            segments.append((t, t + move, views[i - 1][1], offset, None))
            t += move
        segments.append((t, t + rest, offset, offset, i))
        t += rest
    end = t

    def state(ns):
        """(offset, offset velocity per s, index of the image the camera shows)."""
        for t0, t1, a, b, station in segments:
            if t0 <= ns <= t1:
                u = (ns - t0) / (t1 - t0)
                if station is not None:
                    return a, 0.0, station
                s = 3 * u * u - 2 * u * u * u
                ds = (6 * u - 6 * u * u) / ((t1 - t0) / 1e9)
                previous = [i for i, (_, o) in enumerate(views) if o == a][0]
                return a + (b - a) * s, (b - a) * ds, previous
        return views[-1][1], 0.0, len(views) - 1

    writers = []
    paths = []
    if args.split:
        args.out.mkdir(parents=True, exist_ok=True)
    for part in range(2 if args.split else 1):
        path = args.out / f"part{part}" if args.split else args.out
        w = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
        w.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        w.open()
        writers.append(w)
        paths.append(path)
    connections = []
    for w in writers:
        connections.append({
            "image": w.add_connection("/camera/camera/color/image_raw", "sensor_msgs/msg/Image", typestore=ts),
            "info": w.add_connection("/camera/camera/color/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts),
            "tf": w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=ts),
            "tf_static": w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=ts,
                                          offered_qos_profiles=[LATCHED]),
            "joints": w.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=ts),
            "diagnostics": w.add_connection("/diagnostics", "std_msgs/msg/Float64", typestore=ts),
            "infra": w.add_connection("/camera/camera/infra1/image_rect_raw", "sensor_msgs/msg/Image", typestore=ts),
            "infra_info": w.add_connection("/camera/camera/infra1/camera_info", "sensor_msgs/msg/CameraInfo",
                                           typestore=ts),
            "depth": w.add_connection("/camera/camera/depth/image_rect_raw", "sensor_msgs/msg/Image", typestore=ts),
            "yuv": w.add_connection("/camera/camera/color/image_yuv", "sensor_msgs/msg/Image", typestore=ts),
        })
    messages = []  # (log time, kind, payload)

    def put(log_time, kind, message, typename):
        messages.append((log_time, kind, bytes(ts.serialize_cdr(message, typename))))

    static = [tf(start, "wrist_3_link", "flange", (np.zeros(3), axis_angle((0, 1, 0), math.pi / 2))),
              tf(start, "flange", "tool0", compose(inverse((np.zeros(3), axis_angle((0, 1, 0), math.pi / 2))),
                                                   wrist_from_tool0)),
              ]
    put(start, "tf_static", T["tf2_msgs/msg/TFMessage"](transforms=static), "tf2_msgs/msg/TFMessage")
    put(start + 1, "tf_static", T["tf2_msgs/msg/TFMessage"](transforms=[tf(start, "tool0", CAMERA_FRAME, hand_eye)]),
        "tf2_msgs/msg/TFMessage")
    if args.realsense:
        put(start + 2, "tf_static", T["tf2_msgs/msg/TFMessage"](transforms=[
            tf(start, CAMERA_FRAME, "camera_infra1_optical_frame", (np.array([-0.015, 0.0, 0.0]), (0.0, 0.0, 0.0, 1.0)))]),
            "tf2_msgs/msg/TFMessage")
    for ns in range(start, end + 1, 50_000_000):
        offset, _, _ = state(ns)
        put(ns + 2_000_000, "tf", T["tf2_msgs/msg/TFMessage"](
            transforms=[tf(ns, "base_link", "wrist_3_link", wrist_pose(camera_pose(offset)))]), "tf2_msgs/msg/TFMessage")
    for ns in range(start, end + 1, 8_000_000):
        offset, velocity, _ = state(ns)
        positions = np.array([1.0 + 0.5 * offset, -1.2 + 0.25 * offset, 0.3 - 0.5 * offset, -1.5, 1.57, 0.1 * offset])
        velocities = np.array([0.5, 0.25, -0.5, 0.0, 0.0, 0.1]) * velocity
        put(ns + 1_000_000, "joints", T["sensor_msgs/msg/JointState"](
            header=hdr(ns, ""), name=JOINTS, position=positions, velocity=velocities, effort=np.zeros(6)),
            "sensor_msgs/msg/JointState")
    for ns in range(start + 3_000_000, end, 100_000_000):
        _, _, shown = state(ns)
        rgb = views[shown][0]
        height, width = rgb.shape[:2]
        put(ns + 30_000_000, "image", T["sensor_msgs/msg/Image"](
            header=hdr(ns, CAMERA_FRAME), height=height, width=width, encoding="rgb8", is_bigendian=0, step=3 * width,
            data=rgb.reshape(-1)), "sensor_msgs/msg/Image")
        put(ns + 30_000_001, "info", camera_info(hdr(ns, CAMERA_FRAME), width, height, args.focal_px),
            "sensor_msgs/msg/CameraInfo")
        put(ns + 30_000_002, "diagnostics", T["std_msgs/msg/Float64"](data=1.0), "std_msgs/msg/Float64")
        if args.realsense:
            grey = np.ascontiguousarray(rgb.mean(axis=2).astype(np.uint8)[:, ::-1])
            put(ns + 35_000_000, "infra", T["sensor_msgs/msg/Image"](
                header=hdr(ns + 5_000_000, "camera_infra1_optical_frame"), height=height, width=width, encoding="mono8",
                is_bigendian=0, step=width, data=grey.reshape(-1)), "sensor_msgs/msg/Image")
            put(ns + 35_000_001, "infra_info", camera_info(hdr(ns + 5_000_000, "camera_infra1_optical_frame"), width, height, args.focal_px),
                "sensor_msgs/msg/CameraInfo")
            put(ns + 35_000_002, "depth", T["sensor_msgs/msg/Image"](
                header=hdr(ns, "camera_depth_optical_frame"), height=height, width=width, encoding="16UC1",
                is_bigendian=0, step=2 * width, data=np.full(height * width, 800, np.uint16).view(np.uint8)),
                "sensor_msgs/msg/Image")
            put(ns + 35_000_003, "yuv", T["sensor_msgs/msg/Image"](
                header=hdr(ns, CAMERA_FRAME), height=height, width=width, encoding="yuv422",
                is_bigendian=0, step=2 * width, data=np.zeros(height * width * 2, np.uint8)),
                "sensor_msgs/msg/Image")
    messages.sort(key=lambda m: m[0])
    half = messages[len(messages) // 2][0]
    for log_time, kind, data in messages:
        part = 1 if args.split and log_time >= half and kind != "tf_static" else 0
        writers[part].write(connections[part][kind], log_time, data)
    for w in writers:
        w.close()
    if args.split:
        # One bag directory with both storage files, listed in order by its metadata.yaml.
        names = []
        for part, path in enumerate(paths):
            name = f"{args.out.name}_{part}.mcap"
            (path / f"{path.name}.mcap").rename(args.out / name)
            names.append((name, (path / "metadata.yaml").read_text()))
            (path / "metadata.yaml").unlink()
            path.rmdir()
        text = names[0][1].replace("part0.mcap", names[0][0])
        text = text.replace(f"  relative_file_paths:\n  - {names[0][0]}\n",
                            f"  relative_file_paths:\n  - {names[0][0]}\n  - {names[1][0]}\n")
        (args.out / "metadata.yaml").write_text(text)
    poses = {f"{o:g}": [float(v) for v in camera_pose(o)[0]] for _, o in views}
    print(json.dumps({"camera_positions_m": poses, "width": width, "height": height}))


if __name__ == "__main__":
    main()
