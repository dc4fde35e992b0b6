"""What Foxglove needs to show a uwbd log or a live daemon: the schemas of every channel and
the viewer channels (a transform tree, the anchors, trajectories), in one place: the schemas
in :mod:`.schemas`, the raw reads' protobuf in :mod:`.raw`, the viewer channels in :mod:`.view`.

Written by hand, with no dependency (the robot's install stays lean): the ``foxglove.*``
schemas below are Foxglove's own message schemas (its JSON Schema definitions, as the
``foxglove-sdk``'s protobuf descriptors and ``@foxglove/schemas`` publish them), reduced to
the fields uwbd writes; ``tests/test_foxglove.py`` checks them and every logged message
against Foxglove's definitions. uwbd's own channels (``/imu``, ``/uwb``, ``/status``, the
extra fields of ``/pose``) get complete schemas, derived from the frame dataclasses where
they can be.

Every schema stays inside what Foxglove's JSON Schema reader accepts: each property has one
``type`` (``object`` with ``properties``, ``array`` with typed ``items``, ``string``,
``number``, ``integer``, ``boolean``), no ``null`` and no type lists. So a value that is not
known (no reset yet, a field the device does not send) is left out of a record, not written
as ``null``; only a number that is not finite is ``null`` (JSON has no NaN), which the filter
and the drivers do not produce in normal operation.

Times: every record carries ``timestamp {sec, nsec}``, exact in JavaScript, as Foxglove
reads it; ``t_ns`` (integer ns since the Unix epoch) stays for the Python, Rust and C++
clients that read it (above 2^53, so a JavaScript ``JSON.parse`` rounds it: use
``timestamp`` there).

Channels beside the recorded ones:

* ``/tf``, ``foxglove.FrameTransform``: ``nav_frame_id`` → ``body_frame_id`` at each pose;
* ``/anchors``, ``foxglove.SceneUpdate``: a sphere and an id label per anchor, at the start
  of each file and whenever the anchor set changes (live: once a second);
* ``/trajectory``, ``foxglove.PosesInFrame``: the last ``TRAIL_WINDOW_NS`` of poses, one
  every ``TRAIL_SPACING_NS``, once a second;
* ``/truth/trajectory``, ``foxglove.PosesInFrame``: the same for ``/truth`` when there is one.

The trajectory is a ``PosesInFrame``, not a line in a ``SceneUpdate``: it is the standard
path type (Foxglove's 3D panel draws it as a line, arrows or axes, with a gradient; it
maps one to one onto ROS's ``nav_msgs/Path``), it keeps each point's heading, and its
schema is Foxglove's own, so other tools read it as a trajectory too.

``/raw/<source>`` messages are protobuf ``uwbd.Raw { bytes data = 1; }`` (schema: the
serialized ``FileDescriptorSet`` :data:`RAW_DESCRIPTOR`), encoded by hand: the bytes plus a
tag and a length, two bytes for a read under 128 B; logs before this used the schemaless
encoding ``uwbd.raw`` (the bytes as they are), which Foxglove cannot open; both are read.
"""

from uwbd.logs.foxglove.raw import (
    LEGACY_RAW_ENCODING,
    RAW_DESCRIPTOR,
    RAW_MESSAGE_ENCODING,
    RAW_SCHEMA_NAME,
    decode_raw,
    encode_raw,
)
from uwbd.logs.foxglove.schemas import (
    FRAME_TRANSFORM_SCHEMA,
    IMU_SCHEMA,
    POSE_SCHEMA,
    POSES_IN_FRAME_SCHEMA,
    SCENE_UPDATE_SCHEMA,
    SCHEMAS,
    STATUS_SCHEMA,
    TRUTH_SCHEMA,
    UWB_SCHEMA,
    Schema,
    frame_channel,
    stamp,
)
from uwbd.logs.foxglove.view import FoxgloveView, Trail

__all__ = ["FRAME_TRANSFORM_SCHEMA", "IMU_SCHEMA", "LEGACY_RAW_ENCODING", "POSES_IN_FRAME_SCHEMA",
           "POSE_SCHEMA", "RAW_DESCRIPTOR", "RAW_MESSAGE_ENCODING", "RAW_SCHEMA_NAME",
           "SCENE_UPDATE_SCHEMA", "SCHEMAS", "STATUS_SCHEMA", "TRUTH_SCHEMA", "UWB_SCHEMA",
           "FoxgloveView", "Schema", "Trail", "decode_raw", "encode_raw", "frame_channel",
           "stamp"]
