"""A ROS 2 node around gst_jax's stream: people_msgs/msg/People in, the predicted paths and
conformal discs out as visualization_msgs/msg/MarkerArray, the same messages that
`python -m gst_jax.stream replay` writes into a bag (gst_jax.io.ros2 converts both ways).

    python3 node.py --ros-args -p model:=pretrained:crowdnav_sj -p alpha:=0.1

Not tested by gst_jax's suite, which runs without ROS: see README.md beside it.
"""

from __future__ import annotations

import rclpy
from people_msgs.msg import People
from rclpy.node import Node
from rosidl_runtime_py.set_message import set_message_fields
from visualization_msgs.msg import MarkerArray

from gst_jax.conformal import Regions
from gst_jax.errors import DataError
from gst_jax.io import ros2
from gst_jax.runs import load_model
from gst_jax.stream import Stream


class Predictor(Node):
    """Each People message one frame of a Stream, at its header stamp; each frame's markers
    published at once."""

    def __init__(self):
        super().__init__("gst_predictor")
        model = self.declare_parameter("model", "pretrained:crowdnav_sj").value
        alpha = self.declare_parameter("alpha", 0.1).value
        max_people = self.declare_parameter("max_people", 32).value
        self.stream = Stream(load_model(model), regions=Regions("dtaci", alpha))
        self.stream.warm_up(max_people)          # compiled before the first message, not during
        self.names = ros2.TrackNames()
        self.paths = self.create_publisher(MarkerArray, ros2.PREDICTIONS_TOPIC, 10)
        self.discs = self.create_publisher(MarkerArray, ros2.DISCS_TOPIC, 10)
        self.create_subscription(People, ros2.PEOPLE_TOPIC, self.on_people, 10)

    def on_people(self, message: People) -> None:
        try:
            frame = ros2.people_frame(message)
            out = self.stream.step(self.names.ids_of(frame.names), frame.positions,
                                   time=frame.time_s)
        except DataError as error:                # a frame the stream refuses: said, skipped
            self.get_logger().warning(str(error))
            return
        paths, discs = ros2.prediction_markers(out, self.names.names_of(out.ids), frame.header)
        self.paths.publish(marker_array(paths))
        self.discs.publish(marker_array(discs))


def marker_array(markers: dict) -> MarkerArray:
    message = MarkerArray()
    set_message_fields(message, markers)
    return message


def main() -> None:
    rclpy.init()
    node = Predictor()
    try:
        rclpy.spin(node)
    finally:
        node.destroy_node()
        rclpy.shutdown()


if __name__ == "__main__":
    main()
