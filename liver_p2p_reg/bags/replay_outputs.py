"""What a bag replay does with the core's outputs: kept for the row, handed to an observer, written as register_node publishes them."""

from __future__ import annotations

from typing import Any

from liver_p2p_reg.bags.io import (
    DIAGNOSTIC_ARRAY,
    POINTCLOUD2,
    POSE_STAMPED,
    TRANSFORM_STAMPED,
    BagMessage,
    BagWriter,
    rosbags_output_types,
)
from liver_p2p_reg.ros.messages import diagnostic_array, pose_stamped, registered_structures_cloud, transform_stamped
from liver_p2p_reg.ros.pointcloud2 import M_PER_MM, points_to_cloud
from liver_p2p_reg.ros.topics import (
    TOPIC_DEFORMED_PREOP,
    TOPIC_DIAGNOSTICS,
    TOPIC_POSE,
    TOPIC_REGISTERED,
    TOPIC_STRUCTURES,
    TOPIC_TRANSFORM,
)
from liver_p2p_reg.stream.outputs import CoreOutput, Diagnostic

# written with every registration (pose topics with every pose)
OUTPUT_TOPICS = {
    TOPIC_POSE: POSE_STAMPED,
    TOPIC_TRANSFORM: TRANSFORM_STAMPED,
    TOPIC_REGISTERED: POINTCLOUD2,
    TOPIC_STRUCTURES: POINTCLOUD2,
    TOPIC_DIAGNOSTICS: DIAGNOSTIC_ARRAY,
}
# written only when the non-rigid stage was applied (`deform` on)
DEFORM_OUTPUT_TOPICS = {TOPIC_DEFORMED_PREOP: POINTCLOUD2}


class ReplayOutputs:
    """The outputs of one bag's replay, the intraop frame (1-based) each answers, and the output bag they go to.

    `emit` writes what register_node publishes for an output, in its order: pose, transform and the
    registered preop cloud (the rigid pose), then the deformed preop cloud when the non-rigid stage
    was applied, the structures (with every pose) and the diagnostics.
    """

    def __init__(self, writer: BagWriter | None, observer: Any = None) -> None:
        self.writer, self.observer = writer, observer
        self.types = rosbags_output_types()
        self.outputs: list[CoreOutput] = []
        self.output_frames: list[int] = []
        self.frames = 0  # intraop clouds read so far
        self.latest: dict[str, Any] = {}  # the last intraop cloud / fiducials received (the core registers the latest)
        self.last_posed: tuple[CoreOutput, Any, Any, int] | None = None  # (output, its cloud, fiducials, frame)

    def copy_input(self, item: BagMessage) -> None:
        """An input message, into the output bag as it was logged (outputs of an earlier replay are left out)."""
        if self.writer is not None and item.topic not in OUTPUT_TOPICS and item.topic not in DEFORM_OUTPUT_TOPICS:
            self.writer.write(item.topic, item.msgtype, item.timestamp_ns, item.msg)

    def report(self, diagnostics: list[Diagnostic | None], log_ns: int) -> None:
        """Diagnostics about the inputs (the model, its mesh) into the output bag, as the node reports them."""
        kept = [d for d in diagnostics if d is not None]
        if self.writer is not None and kept:
            self.writer.write(TOPIC_DIAGNOSTICS, DIAGNOSTIC_ARRAY, log_ns, diagnostic_array(kept, log_ns, self.types))

    def emit(self, output: CoreOutput | None, stamp_ns: int, log_ns: int) -> None:
        """One output of the core (None: nothing happened), for the frame just read."""
        if output is None:
            return
        if self.observer is not None:
            self.observer.on_output(output)
        self.outputs.append(output)
        self.output_frames.append(self.frames)  # the core registers the latest cloud: the one just received
        if output.pose is not None and output.result is not None:
            self.last_posed = (output, self.latest.get("cloud"), self.latest.get("fiducials"), self.frames)
        writer, types = self.writer, self.types
        if writer is None:
            return
        if output.pose is not None:
            frame_id = output.pose.frame_id
            writer.write(TOPIC_POSE, POSE_STAMPED, log_ns, pose_stamped(output.pose, types))
            writer.write(TOPIC_TRANSFORM, TRANSFORM_STAMPED, log_ns, transform_stamped(output.pose, types))
            writer.write(
                TOPIC_REGISTERED, POINTCLOUD2, log_ns, self._cloud(output.registered_preop_mm, frame_id, stamp_ns)
            )
            if output.deformed_preop_mm is not None:  # only when the non-rigid stage was applied
                cloud = self._cloud(output.deformed_preop_mm, frame_id, stamp_ns)
                writer.write(TOPIC_DEFORMED_PREOP, POINTCLOUD2, log_ns, cloud)
            # with every pose, empty without structures (at their deformed positions when the stage was applied)
            cloud = registered_structures_cloud(output.structures, types.cloud, frame_id, stamp_ns)
            writer.write(TOPIC_STRUCTURES, POINTCLOUD2, log_ns, cloud)
        writer.write(TOPIC_DIAGNOSTICS, DIAGNOSTIC_ARRAY, log_ns, diagnostic_array(output.diagnostics, stamp_ns, types))

    def _cloud(self, points_mm: Any, frame_id: str, stamp_ns: int) -> Any:
        return points_to_cloud(points_mm * M_PER_MM, self.types.cloud, frame_id=frame_id, stamp_ns=stamp_ns)
