"""GatedImages on a real rclpy node: which frames a perception node computes from the grid."""
import rclpy
from sensor_msgs.msg import Image

from ibvs_common.core.modes import InputKind
from ibvs_common.node_common import frame_grid_msg, ns_to_stamp
from ibvs_control.core.rate_governor import SupervisorGrids
from ibvs_perception.config import ImageInputConfig
from ibvs_perception.core.latest_only import LatestOnlyConfig
from ibvs_perception.gated_images import GatedImages

MS = 1_000_000
PERIOD = 20 * MS
EVERY_IMAGE = LatestOnlyConfig(latest_only=False)   # stamps of 1970: ages mean nothing here


def image(stamp_ns):
    msg = Image()
    ns_to_stamp(stamp_ns, msg.header.stamp)
    return msg


def window_gate(node):
    """Return a front-camera GatedImages without mode gating and the stamps it computes."""
    computed = []
    gated = GatedImages(node, InputKind.WINDOW,
                        lambda msg, publish: computed.append(msg.header.stamp.nanosec),
                        'test', ImageInputConfig(mode_gating=False, latest=EVERY_IMAGE),
                        'front', PERIOD)
    return gated, computed


def test_a_smaller_stride_applies_from_its_reference_as_the_supervisor_expects_it(context):
    """The nodes keep the old grid until the smaller stride's first frame, as the supervisor.

    Before, the nodes computed the new grid's frames from the moment they got the grid, while
    the supervisor expected them only after its lead (0.1 s): frames computed for nothing, on
    a slow computer the margin of the try.
    """
    node = rclpy.create_node('gated_grid', context=context)
    try:
        gated, computed = window_gate(node)
        supervisor = SupervisorGrids({'front': PERIOD})
        for stride, at in ((2, 100 * MS), (1, 180 * MS)):   # a try of 1 decided at 180 ms
            supervisor.set_stride('front', stride, at, lead_ns=100 * MS)
            gated.on_grid(frame_grid_msg({'front': (stride, supervisor.ref_ns('front'))}, at))
        stamps = range(200 * MS, 400 * MS, PERIOD)
        for s in stamps:
            gated.on_image(image(s))
        expected = [s for s in stamps if supervisor.on_grid('front', s)]
        assert computed == expected
        # the stride-2 grid of 100 ms until the try's first frame, 100 ms (the lead) later
        assert expected == [220 * MS, 260 * MS] + list(range(280 * MS, 400 * MS, PERIOD))
        # a larger stride applies at once
        supervisor.set_stride('front', 4, 400 * MS, lead_ns=100 * MS)
        gated.on_grid(frame_grid_msg({'front': (4, supervisor.ref_ns('front'))}, 400 * MS))
        computed.clear()
        for s in range(400 * MS, 500 * MS, PERIOD):
            gated.on_image(image(s))
        assert computed == [400 * MS, 480 * MS]
    finally:
        node.destroy_node()


def test_a_flow_node_computes_its_flow_grid_and_a_detector_every_frame_of_the_grid(context):
    """Flows shed: the window detector computes every frame, the front flow every 2nd one."""
    node = rclpy.create_node('gated_flow_grid', context=context)
    try:
        detector, computed = window_gate(node)
        flowed = []
        flow = GatedImages(node, InputKind.FLOW_FRONT,
                           lambda msg, publish: flowed.append(msg.header.stamp.nanosec),
                           'test', ImageInputConfig(mode_gating=False, latest=EVERY_IMAGE),
                           'front', PERIOD, flow=True)
        supervisor = SupervisorGrids({'front': PERIOD})
        supervisor.set_stride('front', 1, 100 * MS, lead_ns=100 * MS, flow_stride=2)
        g = supervisor.flow_grid('front')
        msg = frame_grid_msg({'front': (1, supervisor.ref_ns('front'), g.stride, g.ref_ns)},
                             100 * MS)
        for gated in (detector, flow):
            gated.on_grid(msg)
        stamps = range(120 * MS, 300 * MS, PERIOD)
        for s in stamps:
            detector.on_image(image(s))
            flow.on_image(image(s))
        assert computed == list(stamps)
        assert flowed == list(range(120 * MS, 300 * MS, 2 * PERIOD))
        assert all(supervisor.flow_source_ns('front', s) in flowed for s in stamps)
        assert flow.frame_period_s == 0.04          # the flow's image pairs: 40 ms apart
        # grids given without a flow grid: the flow grid is the frame grid
        flow.on_grid(frame_grid_msg({'front': (1, 0)}, 300 * MS))
        assert flow.grid.stride == 1
    finally:
        node.destroy_node()


def test_a_grid_waiting_in_its_reader_is_applied_before_the_image(context):
    """The node takes the grid (mode, statuses) already waiting before judging an image.

    Behind a busy executor their events wait behind the images that arrived before them:
    a node judged its images on a grid the supervisor had left (frames computed for nothing).
    """
    import time
    from diagnostic_msgs.msg import DiagnosticArray
    from ibvs_common.node_common import MODE_QOS
    node = rclpy.create_node('gated_take', context=context)
    sender = rclpy.create_node('gated_grid_sender', context=context)
    try:
        gated, computed = window_gate(node)
        pub = sender.create_publisher(DiagnosticArray, 'ibvs/frame_grid', MODE_QOS)
        deadline = time.monotonic() + 5.0
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        pub.publish(frame_grid_msg({'front': (4, 0)}, 0))     # every 4th frame from 0
        time.sleep(0.2)                                       # in the reader, not taken
        gated.on_images([image(k * PERIOD) for k in range(1, 9)])
        assert gated.grid.stride == 4
        assert computed == [8 * PERIOD]      # the newest grid image; 1-3, 5-7 off the grid
        assert gated.counts.off_grid == 6 and gated.counts.superseded == 1
    finally:
        sender.destroy_node()
        node.destroy_node()
