"""Publishing poses and status over ZeroMQ as versioned JSON (see README.md, "Pose stream")."""

from edgecal.publish.messages import (
                                      POSE_TOPIC,
                                      SCHEMA_VERSION,
                                      STATUS_TOPIC,
                                      decode,
                                      encode,
                                      pose_message,
                                      status_message,
)
from edgecal.publish.publisher import DEFAULT_ENDPOINT, PosePublisher, check_endpoint, is_local_endpoint

__all__ = ["DEFAULT_ENDPOINT", "POSE_TOPIC", "PosePublisher", "SCHEMA_VERSION", "STATUS_TOPIC", "check_endpoint",
           "decode", "encode", "is_local_endpoint", "pose_message", "status_message"]
