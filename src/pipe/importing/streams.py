"""Readers of recordings that keep the wrench and the pose as separate streams with their own time stamps:
ROS 1 and ROS 2 bags (through the pure-Python `rosbags` library) and HDF5 files in the layout of the LABIT
assembly benchmark. The pose is interpolated onto the wrench's time stamps (position linearly, orientation
by spherical linear interpolation), and only the wrench samples inside the pose's time span are kept."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from pipe.data.spec import length_to_mm
from pipe.errors import DatasetError
from pipe.importing.readers import ReaderOptions, register
from pipe.importing.recording import Recording, interpolate_onto, overlap

WRENCH_TYPE = "geometry_msgs/msg/WrenchStamped"
POSE_TYPE = "geometry_msgs/msg/PoseStamped"
TF_TOPICS = ("/tf", "/tf_static")


def aligned(path: Path, wrench_time: np.ndarray, force: np.ndarray, pose_time: np.ndarray, position_mm: np.ndarray,
            rotation: Rotation, options: ReaderOptions) -> Recording:
    """The recording at the wrench's time stamps inside the pose stream's span."""
    order = np.argsort(pose_time, kind="stable")
    pose_time, unique = np.unique(pose_time[order], return_index=True)    # a repeated pose stamp is dropped
    if len(pose_time) < 2:
        raise DatasetError(f"the pose stream has {len(pose_time)} distinct time stamp(s); at least 2 are needed", path)
    position_mm, rotation = position_mm[order][unique], rotation[order][unique]
    inside = overlap(path, wrench_time, pose_time, "pose")
    time = wrench_time[inside]
    return Recording(path, time, interpolate_onto(time, pose_time, position_mm), force[inside],
                     rotation=Slerp(pose_time, rotation)(time).as_rotvec(),
                     force_in_tool_frame=options.force_in_tool_frame)


def _stamp(header) -> float:
    return header.stamp.sec + 1e-9 * header.stamp.nanosec


@register("rosbag", ("*.bag",), "ROS 1 (.bag) or ROS 2 (folder with metadata.yaml) bag: a WrenchStamped topic "
                                "(--wrench-topic) and a PoseStamped topic (--pose-topic) or TF (--tf PARENT,CHILD)",
          folder_marker="metadata.yaml")
def read_bag(path: Path, options: ReaderOptions) -> Recording:
    from rosbags.highlevel import AnyReader

    try:
        reader = AnyReader([path])
        reader.open()
    except Exception as exc:  # rosbags raises its own error type per storage format
        raise DatasetError(f"not a readable ROS bag ({type(exc).__name__}: {exc})", path) from None
    try:
        connections = {}
        for connection in reader.connections:
            connections.setdefault(connection.topic, []).append(connection)

        def messages(topic: str, msgtype: str) -> list:
            if topic not in connections:
                raise DatasetError(f"has no topic {topic!r}; its topics are {sorted(connections)}", path)
            found = {c.msgtype for c in connections[topic]}
            if found != {msgtype}:
                raise DatasetError(f"topic {topic!r} carries {sorted(found)}, not {msgtype}", path)
            return [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(connections=connections[topic])]

        wrenches = messages(options.wrench_topic, WRENCH_TYPE)
        wrench_time = np.array([_stamp(m.header) for m in wrenches])
        force = np.array([[m.wrench.force.x, m.wrench.force.y, m.wrench.force.z] for m in wrenches]).reshape(-1, 3)
        if options.tf_frames is None:
            poses = [(_stamp(m.header), m.pose.position, m.pose.orientation)
                     for m in messages(options.pose_topic, POSE_TYPE)]
        else:
            parent, child = options.tf_frames
            tf_topics = [t for t in TF_TOPICS if t in connections]
            if not tf_topics:
                raise DatasetError(f"has no /tf topic for the pose from {parent!r} to {child!r}; its topics are "
                                   f"{sorted(connections)}", path)
            transforms = [t for topic in tf_topics for m in messages(topic, "tf2_msgs/msg/TFMessage")
                          for t in m.transforms]
            poses = [(_stamp(t.header), t.transform.translation, t.transform.rotation) for t in transforms
                     if t.header.frame_id.lstrip("/") == parent.lstrip("/")
                     and t.child_frame_id.lstrip("/") == child.lstrip("/")]
            if not poses:
                pairs = sorted({f"{t.header.frame_id}->{t.child_frame_id}" for t in transforms})
                raise DatasetError(f"/tf has no transform from {parent!r} to {child!r}; it has {pairs}", path)
    finally:
        reader.close()
    if len(wrench_time) < 2:
        raise DatasetError(f"topic {options.wrench_topic!r} has {len(wrench_time)} message(s); at least 2 are needed",
                           path)
    pose_time = np.array([p[0] for p in poses])
    position = np.array([[p[1].x, p[1].y, p[1].z] for p in poses]) * 1000.0      # ROS lengths are metres
    rotation = Rotation.from_quat([[p[2].x, p[2].y, p[2].z, p[2].w] for p in poses])
    return aligned(path, wrench_time, force, pose_time, position, rotation, options)


@register("hdf5", ("*.h5", "*.hdf5"), "HDF5 in the LABIT benchmark's layout: /wrench/data (N, 6), /pose/data (M, 7: "
                                      "position, quaternion), each with its time stamps (names configurable)")
def read_hdf5(path: Path, options: ReaderOptions) -> Recording:
    import h5py

    if options.quaternion not in ("xyzw", "wxyz"):
        raise DatasetError(f"quaternion order {options.quaternion!r} is not xyzw or wxyz")
    try:
        handle = h5py.File(path, "r")
    except OSError as exc:
        raise DatasetError(f"not a readable HDF5 file ({exc})", path) from None
    with handle:
        names: list[str] = []
        handle.visititems(lambda name, obj: names.append(name) if isinstance(obj, h5py.Dataset) else None)
        arrays = {}
        for key, shape in (("wrench_data", 6), ("wrench_time", None), ("pose_data", 7), ("pose_time", None)):
            name = getattr(options, key)
            if name.strip("/") not in names:
                raise DatasetError(f"has no dataset {name!r}; its datasets are {names}", path)
            values = np.asarray(handle[name][()], dtype=float)
            if (values.ndim != 1) if shape is None else (values.ndim != 2 or values.shape[1] < shape):
                want = "(N,)" if shape is None else f"(N, {shape})"
                raise DatasetError(f"dataset {name!r} has shape {values.shape}, expected {want}", path)
            arrays[key] = values
    for data, time in (("wrench_data", "wrench_time"), ("pose_data", "pose_time")):
        if len(arrays[data]) != len(arrays[time]):
            raise DatasetError(f"{getattr(options, data)!r} has {len(arrays[data])} rows but "
                               f"{getattr(options, time)!r} has {len(arrays[time])}", path)
        if not np.isfinite(arrays[data]).all() or not np.isfinite(arrays[time]).all():
            raise DatasetError(f"{getattr(options, data)!r} or its time stamps hold NaN or infinite values", path)
    pose = arrays["pose_data"]
    quaternion = pose[:, 3:7] if options.quaternion == "xyzw" else pose[:, [4, 5, 6, 3]]
    return aligned(path, arrays["wrench_time"], arrays["wrench_data"][:, :3], arrays["pose_time"],
                   pose[:, :3] * length_to_mm(options.position_unit), Rotation.from_quat(quaternion), options)
