"""The sim node's logic without ROS: frame 0's hold, /clock first, faults, products, stats."""
import pytest

from ibvs_common.core.config import load_pad_layout, load_vehicle
from ibvs_sim.config import SimNodeConfig
from ibvs_sim.core.graph_sync import STATUS_TOPIC
from ibvs_sim.core.world import load_world
from ibvs_sim.driver import FAULT_ANSWER_WAIT_S, SimDriver

KERNEL_PORT = 'udpin:127.0.0.1:0'     # the autopilot on a port the kernel picks


class FakePort:
    """Records what the driver publishes; the graph's subscriber and publisher counts."""

    def __init__(self, subscribers=0, publishers=1):
        self.calls = []
        self.subscribers, self.publishers = subscribers, publishers

    def publish_clock(self, t_ns):
        self.calls.append(('clock', t_ns))

    def publish_images(self, images, stamps_ns):
        self.calls.append(('images', dict(stamps_ns), sorted(images)))

    def publish_ground_truth(self, t_ns, state):
        self.calls.append(('truth', t_ns))

    def publish_event(self, event):
        self.calls.append(('event', event.type.value))

    def count_image_subscribers(self):
        return {'front': self.subscribers, 'down': self.subscribers}

    def count_publishers(self, topic):
        return self.publishers


class FakeLog:
    def __init__(self):
        self.lines = []

    def info(self, message, **kwargs):
        self.lines.append(('info', message))

    def warning(self, message, **kwargs):
        self.lines.append(('warning', message))

    def error(self, message, **kwargs):
        self.lines.append(('error', message))


@pytest.fixture(scope='module')
def configs():
    return load_world(), load_pad_layout(), load_vehicle()


def _driver(configs, port, **params):
    cfg = SimNodeConfig(mavlink_url=KERNEL_PORT, start_on_setpoints=False, **params)
    return SimDriver(*configs, cfg, port=port, log=FakeLog())


def test_frame_0_waits_for_its_subscribers_then_goes_clock_first(configs):
    port = FakePort(subscribers=0)
    driver = _driver(configs, port, min_image_subscribers=2, subscriber_wait_timeout_s=60.0)
    try:
        driver.tick()
        assert port.calls == [] and driver.sim.frame_index == -1       # held: no subscribers
        assert any('frame 0 waits for the graph' in m for _, m in driver.log.lines)
        port.subscribers = 2
        driver.first_frame_hold.settle_s = 0.0
        driver.tick()
        # lockstep: /clock of the frame before anything of it; then images and ground truth
        assert port.calls[0] == ('clock', 0)
        frames = [c for c in port.calls if c[0] != 'clock']
        assert frames == [('images', {'front': 0, 'down': 0}, ['down', 'front']), ('truth', 0)]
        assert driver.products.frame_ns == 0
        assert driver.products.status_expected and STATUS_TOPIC not in driver.products.expected
        assert len(driver.products.expected) == 5                  # both cameras' products
        driver.tick()                                              # no answer: no frame
        assert [c for c in port.calls if c[0] != 'clock'] == frames
        stats = driver.stats()
        assert stats['pacing'] == 'lockstep' and stats['frames_published'] == 1
        assert stats['lockstep_timeouts'] == 0 and 'wall_render_ms_per_frame' in stats
    finally:
        driver.close()


def test_a_camera_off_is_withheld_and_its_frame_waited_for_briefly(configs):
    port = FakePort()
    driver = _driver(configs, port, fault_front_camera_off_s=[0.0, 1.0])
    try:
        driver.tick()
        assert ('images', {'down': 0}, ['down']) in port.calls
        assert driver.sim.lockstep.answer_wait_s == FAULT_ANSWER_WAIT_S
        assert not {'window/corners', 'front_camera/translational_flow'} \
            & driver.products.expected                             # no front images: none
        assert any('front camera off' in m for _, m in driver.log.lines)
    finally:
        driver.close()


def test_a_bad_parameter_combination_is_refused_naming_it():
    with pytest.raises(ValueError, match='pacing'):
        SimNodeConfig(pacing='fast')
    with pytest.raises(ValueError, match='fault_imu_off_s'):
        SimNodeConfig(fault_imu_off_s=[1.0, 2.0, 3.0, 4.0])
    with pytest.raises(ValueError, match='fault_down_camera_freeze_s'):
        SimNodeConfig(fault_down_camera_freeze_s=[2.0, 1.0])
    with pytest.raises(ValueError, match='wind_force_map'):
        SimNodeConfig(wind_force_map=[0.0, 1.0])


def test_a_failed_pre_roll_never_starts_the_clock_afterwards(configs):
    """A firmware's pre-roll that failed (not still at the start in time) ends the run: the
    sim never starts its clock when the vehicle holds later (a campaign run did, with the sim
    ended, and the harness waited for frames that could not come)."""
    from ibvs_sim.core.firmware.px4_hil import FirmwareLinkError

    class Firmware:
        ready, calls = False, 0

        def preroll(self, steps):
            self.calls += 1
            if self.calls == 1:
                raise FirmwareLinkError('pre-roll: not holding at the start 300 s after boot')
            return True                      # it would hold now

    port = FakePort(subscribers=2)
    driver = _driver(configs, port, min_image_subscribers=2)
    try:
        driver.firmware = Firmware()
        for _ in range(3):
            driver.tick()
        assert driver.firmware.calls == 1 and driver.sim.ended
        assert port.calls == [] and driver.sim.frame_index == -1
        assert any('pre-roll' in m for level, m in driver.log.lines if level == 'error')
    finally:
        driver.firmware = None
        driver.close()
