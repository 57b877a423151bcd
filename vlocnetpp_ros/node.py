"""``localizer``: the VLocNet++ ROS 2 node
(``ros2 run vlocnetpp_ros localizer --ros-args --params-file config/localizer.yaml``).

Subscribes to a camera (``sensor_msgs/Image`` rgb8 / bgr8 / rgba8 / bgra8 / mono8, or
``CompressedImage`` on ``<image_topic>/compressed`` with ``use_compressed``), optionally an
aligned depth image (32FC1 metres or 16UC1 millimetres, matched to the colour image by stamp)
and ``CameraInfo``, and publishes for every processed frame, with the input stamp:

* ``vlocnet/pose`` (``PoseStamped`` in ``map_frame``): global camera pose, or with ``base_frame``
  set the pose of ``base_frame`` (``T_map,base = T_map,camera camera_extrinsics^{-1}``,
  :mod:`vlocnetpp_core.camera.extrinsics`); with a keyframe map (parameter ``map``) the refined pose, or
  between refinements (``refine_every``) the propagated one, else the network's;
* ``vlocnet/pose_with_covariance`` (``PoseWithCovarianceStamped``, same stamp, frame and pose): with
  the calibrated 6x6 covariance (robot_localization's input; that of the refinement when refined);
* ``vlocnet/network_pose`` (``PoseStamped``, same stamp and frame): only with a map, the network's own pose;
* ``vlocnet/odometry`` (``Odometry`` in ``odom_frame``, child ``base_frame`` or the image's
  frame): pose accumulated from the odometry stream, twist = relative motion / dt, covariances
  from the checkpoint calibration; of the base when ``base_frame`` is set;
* ``vlocnet/segmentation`` (``Image`` mono8, the input's frame): class id per pixel; advertised
  only with ``publish_segmentation`` and a model that has a semantic stream;
* ``/diagnostics`` (1 Hz): rates, latency, dropped, rejected by reason, resets by reason; with a map the
  share of frames refined and the refinement's outcomes (:mod:`vlocnetpp_ros.diagnostics`).

Parameters: :mod:`vlocnetpp_ros.parameters` (``config/localizer.yaml`` sets every one).

All numbers come from :class:`vlocnetpp_core.inference.localizer.Localizer`; this node only converts
messages. The subscription callback only drops the message into a one-slot mailbox (never
blocks); a worker thread takes the newest frame through the network (``Localizer.begin``), so a camera faster
than the model has its older frames dropped and counted, and hands it to a second thread that refines it and
publishes (``Localizer.finish``) while the next frame's network runs: at most one frame waits between the two.
Camera topics use reliability ``BEST_AVAILABLE``: reliable
delivery from a reliable camera, and a best-effort camera still connects (see docs/node.md
for the transport settings large best-effort streams need). A bad frame (encoding, size,
truncated data, NaN output, ...) is logged (throttled), counted and skipped; the node keeps going.

Memory does not grow with bad input: a camera or depth message that its header and data length
already show to be unusable is refused in the subscription callback (it never takes the mailbox
slot of a good frame, nor a place among the depth images kept for matching), and nothing keeps
a reference to a refused message, its buffer or its exception once the callback or the frame
is done; counters and throttled log keys are bounded (see :mod:`vlocnetpp_ros.diagnostics`).
Once a second, after the diagnostics, the heap pages freed since are handed back to the system
(glibc ``malloc_trim``, :mod:`vlocnetpp_ros.heap`), so the resident memory follows the memory in use after bursts
of large messages instead of staying at their high-water mark; the diagnostics say how much that is
(``heap_in_use_mb``). The ``localizer`` program gives its Fast DDS
readers the ``DYNAMIC`` history memory policy (:mod:`vlocnetpp_ros.dds_profile`), so the transport's
buffers stay bounded too, whatever the history depth of the publishers, and its shared-memory transport an 8 MiB
segment, so that its large messages (segmentation) are not delayed (a camera needs the same: docs/node.md).
"""

from __future__ import annotations

import gc
import queue
import sys
import threading
import time
from pathlib import Path

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, KeyValue
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.exceptions import NameValidationException, ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header

from vlocnetpp_core.bag import topics
from vlocnetpp_core.camera.extrinsics import CameraExtrinsics, base_pose, to_base_frame
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.inference.localizer import Localizer
from vlocnetpp_core.inference.preprocess import FrameError
from vlocnetpp_core.threads import resolve_threads, use_threads
from vlocnetpp_ros import conversions, dds_profile
from vlocnetpp_ros.depth_matcher import DepthMatcher
from vlocnetpp_ros.diagnostics import NodeStats, ThrottledLog
from vlocnetpp_ros.heap import Heap
from vlocnetpp_ros.mailbox import LatestMailbox
from vlocnetpp_ros.parameters import PARAMETERS, check_parameters, default_checkpoint, extrinsics_of, map_of

# Keep-last 10, the depth of ROS's default (reliable) publisher profile. A reliable subscription whose
# history is shallower than the publisher's window grows in Fast DDS 2.14 when large (fragmented)
# messages of varying sizes overflow it, with rmw_fastrtps's PREALLOCATED_WITH_REALLOC readers; the
# localizer program gives its readers the DYNAMIC policy instead (vlocnetpp_ros/dds_profile.py), flat
# for publishers of any depth (docs/node.md, "Memory under bad input"). Bounded: at most 10 messages
# wait in DDS, the callback moves them to the one-slot mailbox at once.
CAMERA_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.BEST_AVAILABLE)


class LocalizerNode(Node):
    """The node; raises :class:`UserError` at construction when the checkpoint cannot be used."""

    def __init__(self, **kwargs):
        super().__init__("localizer", **kwargs)
        for name, (default, description) in PARAMETERS.items():
            # camera_extrinsics: any type, checked below, so that [0, 0, 0, 1, 0, 0, 0] (integers) is accepted too
            self.declare_parameter(
                name,
                default,
                ParameterDescriptor(
                    description=description, read_only=True, dynamic_typing=name == "camera_extrinsics"
                ),
            )
        p = {name: self.get_parameter(name).value for name in PARAMETERS}
        self.params = p
        check_parameters(p)
        self.extrinsics = extrinsics_of(p)
        checkpoint = Path(p["checkpoint"]) if p["checkpoint"] else default_checkpoint()
        map_path = map_of(p, checkpoint, self.get_logger().warning)
        self.localizer = Localizer.from_checkpoint(
            checkpoint,
            device=p["device"],
            max_gap_s=p["max_gap_s"],
            num_threads=resolve_threads(p["num_threads"]),
            backend=p["backend"],
            map_path=map_path,
            refine_every=p["refine_every"],
            fuse_odometry=p["fuse_odometry"],
        )
        w, h = self.localizer.input_size
        self.stats = NodeStats(
            info={
                "checkpoint": str(checkpoint),
                "device": str(p["device"]),
                "backend": p["backend"],
                "input_size": f"{w}x{h}",
                "map": str(map_path or "none"),
            },
            refinement=map_path is not None,
        )
        self.warn = ThrottledLog(self.get_logger().warning)
        # a call site of its own: rclpy refuses two severities logged from one line (ThrottledLog's)
        self.note = ThrottledLog(lambda line: self.get_logger().info(line))
        self._mailbox = LatestMailbox()
        self._begun: queue.Queue = queue.Queue(maxsize=1)  # frames past the network, waiting for the publisher stage
        self._intrinsics = None
        self._depths = DepthMatcher(self._ignore)

        # outputs in the node's namespace (topics.py names them as in the root namespace)
        self.pose_pub = self.create_publisher(PoseStamped, topics.POSE_TOPIC.lstrip("/"), 10)
        self.pose_cov_pub = self.create_publisher(
            PoseWithCovarianceStamped, topics.POSE_WITH_COVARIANCE_TOPIC.lstrip("/"), 10
        )
        self.odom_pub = self.create_publisher(Odometry, topics.ODOMETRY_TOPIC.lstrip("/"), 10)
        self.seg_pub = None  # advertised only when there is something to publish
        if p["publish_segmentation"] and self.localizer.has_segmentation:
            self.seg_pub = self.create_publisher(Image, topics.SEGMENTATION_TOPIC.lstrip("/"), 10)
        elif p["publish_segmentation"]:
            self.get_logger().info("the model has no semantic stream: vlocnet/segmentation is not advertised")
        self.network_pose_pub = None  # the network's own pose beside the refined one: only with a map
        if map_path is not None:
            self.network_pose_pub = self.create_publisher(PoseStamped, topics.NETWORK_POSE_TOPIC.lstrip("/"), 10)
        self.diag_pub = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS_TOPIC, 10)
        image_topic = p["image_topic"].rstrip("/") + "/compressed" if p["use_compressed"] else p["image_topic"]
        self._inputs = {image_topic: (CompressedImage if p["use_compressed"] else Image, self._on_image)}
        if p["depth_topic"]:
            self._inputs[p["depth_topic"]] = (Image, self._depths.add)
        if p["camera_info_topic"]:
            self._inputs[p["camera_info_topic"]] = (CameraInfo, self._on_camera_info)
        self._subscriptions_by_topic: dict[str, object] = {}
        self._incompatible: set[str] = set()
        for topic in self._inputs:
            self._subscribe(topic)
        self._heap = Heap()
        self.create_timer(1.0, self._publish_diagnostics)
        self.create_timer(0.5, self._resubscribe_incompatible)

        self._stop = threading.Event()
        self._workers = [
            threading.Thread(target=target, name=name, daemon=True)
            for target, name in ((self._work, "vlocnetpp-inference"), (self._finish_and_publish, "vlocnetpp-publish"))
        ]
        for worker in self._workers:
            worker.start()
        extrinsics = (self.extrinsics or CameraExtrinsics.identity()).values()
        pose_of = f"{p['base_frame']} (camera_extrinsics {extrinsics})" if p["base_frame"] else "the camera"
        refining = (
            f"refined against {map_path} every {p['refine_every']} frame(s)" if map_path else "no refinement (no map)"
        )
        self.get_logger().info(
            f"localizer ready: {checkpoint} on {p['device']} ({p['backend']}, "
            f"network input {w}x{h}), camera {image_topic}, "
            f"publishing the pose of {pose_of}, {refining}"
        )

    # ------------------------------------------------------------------ subscriptions

    def _subscribe(self, topic: str) -> None:
        """(Re)create the subscription of an input topic with reliability BEST_AVAILABLE.

        BEST_AVAILABLE is resolved against the publishers present when the subscription is made
        (none at start-up: reliable). A best-effort camera that starts later is reported as
        incompatible; the subscription is then made again, which resolves to best effort.
        """
        old = self._subscriptions_by_topic.pop(topic, None)
        if old is not None:
            self.destroy_subscription(old)
        msg_type, callback = self._inputs[topic]
        events = SubscriptionEventCallbacks(incompatible_qos=lambda _status, topic=topic: self._incompatible.add(topic))
        self._subscriptions_by_topic[topic] = self.create_subscription(
            msg_type, topic, callback, CAMERA_QOS, event_callbacks=events
        )

    def _resubscribe_incompatible(self) -> None:
        for topic in list(self._incompatible):
            self._incompatible.discard(topic)
            self.get_logger().info(
                f"a publisher on {topic} offers incompatible QoS (a best-effort camera started after this node?): "
                "subscribing again so that BEST_AVAILABLE matches it"
            )
            self._subscribe(topic)

    # ------------------------------------------------------------------ callbacks (never block)

    def _on_image(self, msg) -> None:
        now = time.monotonic()
        try:
            conversions.check_image(msg)
        except FrameError as err:  # refused from its header: never displaces a good frame in the mailbox
            self.stats.arrived(now, False)
            self._reject(err)
            return
        self.stats.arrived(now, self._mailbox.put((msg, now)))

    def _on_camera_info(self, msg: CameraInfo) -> None:
        try:
            self._intrinsics = conversions.camera_info_to_intrinsics(msg)
        except FrameError as err:
            self._ignore(err)

    # ------------------------------------------------------------------ workers: network, then refinement and outputs

    def _work(self) -> None:
        """First stage: the newest frame through the network (:meth:`Localizer.begin`), handed to the second stage
        (which may still refine and publish the frame before: the next frame's network runs meanwhile)."""
        while not self._stop.is_set():
            item = self._mailbox.take(timeout=0.2)
            if item is None:
                continue
            try:
                begun = self._begin(*item)
                while not self._stop.is_set():
                    try:
                        self._begun.put(begun, timeout=0.2)
                        break
                    except queue.Full:
                        continue
            except FrameError as err:
                self._reject(err)
            except Exception as err:  # the node never dies on a frame
                if self._stop.is_set() or not rclpy.ok(context=self.context):
                    return
                self._reject(FrameError("internal_error", f"{type(err).__name__}: {err}"))
            finally:
                item = begun = None  # the message and its buffers go now, not when the next frame arrives

    def _begin(self, msg, arrival: float) -> tuple:
        if isinstance(msg, CompressedImage):
            image, encoding = conversions.compressed_to_rgb(msg), "rgb8"
        else:
            image, encoding = conversions.image_to_array(msg), msg.encoding
        stamp = conversions.stamp_to_seconds(msg.header.stamp)
        depth = self._depths.matching(msg.header.stamp) if self.params["depth_topic"] else None
        try:
            step = self.localizer.begin(image, encoding, stamp, depth=depth, intrinsics=self._intrinsics)
        except FrameError as err:
            if depth is None or err.reason != "depth_size":
                raise
            self._ignore(err)  # use the predicted depth for this frame
            step = self.localizer.begin(image, encoding, stamp, intrinsics=self._intrinsics)
        return msg.header, arrival, step

    def _finish_and_publish(self) -> None:
        """Second stage, in the order of the first: the refinement (:meth:`Localizer.finish`) and every output."""
        while not self._stop.is_set():
            try:
                begun = self._begun.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                self._publish(begun[0], begun[1], self.localizer.finish(begun[2]))
            except Exception as err:  # the node never dies on a frame
                if self._stop.is_set() or not rclpy.ok(context=self.context):
                    return
                self._reject(FrameError("internal_error", f"{type(err).__name__}: {err}"))
            finally:
                begun = None

    def _publish(self, header: Header, arrival: float, result) -> None:
        stamp = result.stamp
        if result.reset_reason not in (None, "start"):
            self.note(
                f"reset.{result.reset_reason}", f"temporal state reset ({result.reset_reason}) at stamp {stamp:.3f}"
            )
        frame = header.frame_id
        network = (result.network_t, result.network_q)
        if self.extrinsics is not None:
            network = base_pose(*network, self.extrinsics)
            result = to_base_frame(result, self.extrinsics)
        pose_header = Header(stamp=header.stamp, frame_id=self.params["map_frame"])
        self.pose_pub.publish(conversions.pose_stamped(result, pose_header))
        if self.network_pose_pub is not None:
            self.network_pose_pub.publish(PoseStamped(header=pose_header, pose=conversions.pose_msg(*network)))
        self.pose_cov_pub.publish(conversions.pose_with_covariance(result, pose_header))
        self.odom_pub.publish(
            conversions.odometry(
                result,
                Header(stamp=header.stamp, frame_id=self.params["odom_frame"]),
                self.params["base_frame"] or frame,
            )
        )
        if self.seg_pub is not None:
            self.seg_pub.publish(conversions.mask_to_image(result.mask, Header(stamp=header.stamp, frame_id=frame)))
        now = time.monotonic()
        self.stats.processed_frame(now, now - arrival, result.reset_reason, result.source, result.refine_status)

    def _reject(self, err: FrameError) -> None:
        """A camera frame skipped."""
        self.stats.reject(err.reason)
        self.warn(err.reason, f"frame skipped ({err.reason}): {err}")

    def _ignore(self, err: FrameError) -> None:
        """A side input (depth, camera info) not used; the frame itself is still processed."""
        self.stats.ignore(err.reason)
        self.warn(err.reason, f"ignored ({err.reason}): {err}")

    def _publish_diagnostics(self) -> None:
        status = self.stats.status("vlocnetpp_ros: localizer", self.get_fully_qualified_name())
        in_use = self._heap.in_use_mb()
        if in_use is not None:
            status.values.append(KeyValue(key="heap_in_use_mb", value=f"{in_use:.1f}"))
        self.diag_pub.publish(DiagnosticArray(header=Header(stamp=self.get_clock().now().to_msg()), status=[status]))
        self._heap.trim()

    def close(self, timeout_s: float = 1.5) -> None:
        """Stop the workers (each finishes its frame in progress, at most ``timeout_s``)."""
        self._stop.set()
        self._mailbox.close()
        for worker in self._workers:
            worker.join(timeout_s)


def main(args: list[str] | None = None) -> int:
    """Entry point; returns 0 after SIGINT/SIGTERM, 1 when the node cannot start (one log line says why).

    Before ``rclpy.init`` the process's Fast DDS participant is given the history memory policy that
    keeps its memory bounded under bursts from any publisher (:mod:`vlocnetpp_ros.dds_profile`, merged
    with the user's profile file; the environment is restored once the participant exists)."""
    profile = dds_profile.apply()
    rclpy.init(args=args)
    node = None
    code = 0
    try:
        node = LocalizerNode()
        profile.restore()  # the participant exists: Fast DDS has read the profile
        node.get_logger().info(profile.message)
        use_threads(node.params["num_threads"])  # torch's threads are the process's: set by the program, not the node
        # Everything loaded so far (torch, the model) lives until exit: keep it out of the garbage
        # collector's scans. Fewer pauses while streaming, and exit after a signal takes ~0.2 s
        # instead of ~1 s (finalisation otherwise walks every torch object).
        gc.freeze()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (UserError, ParameterException, NameValidationException) as err:
        rclpy.logging.get_logger("localizer").error(f"cannot start: {err}")
        code = 1
    except Exception:
        if rclpy.ok():
            raise
        # SIGINT/SIGTERM while starting: rclpy shut the context down under the constructor
    finally:
        profile.restore()
        if node is not None:
            node.close()
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
