"""Fakes at the vendor-SDK boundary only: ur-rtde modules, a depthai module, cv2.VideoCapture.

Each fake records the calls it receives so tests can assert on what the driver told the "SDK".
"""

from __future__ import annotations

import datetime
import threading
import time
import types

import numpy as np

from robot_io.arms.base import Arm, Fault, tcp_from_joints
from robot_io.poses import pose_from_vec, pose_to_vec

# ---------------------------------------------------------------------------- joint-commanded arms

#: A UR5 configuration with the tool pointing down, its TCP about 0.49 m in front of the base and
#: 0.43 m above it, away from every joint limit and singularity.
Q_UR5_READY = (0.0, -1.571, 1.571, -1.571, -1.571, 0.0)


def ur5_scene_arm(control_period_s: float = 0.05, T_base_link=None, T_tool_tcp=None):
    """The shipped UR5 as a :class:`sim.ik.SceneArm`, home :data:`Q_UR5_READY`: its ``base_link`` at
    ``T_base_link`` in the arm's base frame (default: that frame), its TCP at ``T_tool_tcp`` in
    ``tool0`` (default: ``tool0``)."""
    from sim.ik import SceneArm
    from sim.kinematics import shipped_arm

    T_base_link = np.eye(4) if T_base_link is None else np.asarray(T_base_link, dtype=np.float64)
    T_tool_tcp = np.eye(4) if T_tool_tcp is None else np.asarray(T_tool_tcp, dtype=np.float64)
    return SceneArm(shipped_arm("ur5"), T_base_link, T_tool_tcp, control_period_s, np.array(Q_UR5_READY))


# ---------------------------------------------------------------------------- ur-rtde


class FakeURController:
    """The robot side shared by the three fake ur-rtde interfaces.

    Models what the driver must get right in time, on the wall clock:

    * the RTDE watchdog: after ``setWatchdog(hz)`` every input update the control interface sends
      (``kickWatchdog`` and every command) must come within ``1 / hz`` of the previous one, or the
      control script stops (ur-rtde's watchdog action is "stop"); ``stopScript`` disarms it.
      ``feed_gaps_s`` records every gap, ``watchdog_tripped`` whether one was too long.
    * ``moveL`` takes ``distance / speed``: blocking, it returns after that long; asynchronous, it
      returns at once and ``getAsyncOperationProgressEx`` reports the operation (its id is bumped
      when it starts; for ``stale_polls`` reads after ``moveL`` returns the register still shows the
      previous operation, as when the control script has not started the move thread yet).
      ``stopL`` ends it where the TCP is; ``stall_moves`` makes moves never finish;
      ``protective_stop_after_s`` raises a protective stop that long into a move (which freezes it);
      ``reject_moves`` makes ``moveL``/``moveJ`` return False with no fault raised, as the
      controller does for a target it cannot reach.
    * joints ``q`` (``getActualQ``): ``servoJ`` sets them, ``moveJ`` moves them like ``moveL`` moves
      the TCP (the leading joint at ``speed``; ``stopJ`` ends it). Given ``kinematics`` (a
      :class:`sim.ik.SceneArm`), the TCP follows their FK and starts at the FK of ``q_home``;
      without it, the joints are tracked alone. TCP commands (``servoL``, ``moveL``) move the TCP
      only, never the joints.
    """

    def __init__(self, pose=(0.4, 0.0, 0.3, 3.14159, 0.0, 0.0), kinematics=None):
        self.kinematics = kinematics
        self.pose = list(pose)
        self.q = [0.0] * 6
        if kinematics is not None:
            self.set_q(kinematics.q_home)
        self.calls: list[tuple] = []
        self.protective_stopped = False
        self.emergency_stopped = False
        self.program_running = True
        self.connected = True
        self.fail_connect = False
        self.fail_control_init = False
        self.fail_set_watchdog = False
        self.serial_number: str | None = "20235500042"  # None: a DashboardClient without getSerialNumber
        self.robot_model = "UR5"
        self.dashboard_unreachable = False
        self.has_async_status = True
        # watchdog
        self.watchdog_hz: float | None = None
        self.last_feed_s: float | None = None
        self.feed_gaps_s: list[float] = []
        self.watchdog_tripped = False
        self.trip_stops_script = True  # False: record a trip but keep running (call-order tests on a loaded machine)
        # motion
        self.move: dict | None = None
        self.op_id = 0
        self.stale_polls = 2
        self.stall_moves = False
        self.protective_stop_after_s: float | None = None
        self.reject_moves = False  # moveL/moveJ answer False with no fault (a target the controller cannot reach)

    def log(self, *call):
        self.calls.append(call)

    def set_q(self, q) -> None:
        """The joints are ``q``; with kinematics the TCP is their FK."""
        self.q = [float(x) for x in q]
        if self.kinematics is not None:
            self.pose = pose_to_vec(tcp_from_joints(self.kinematics, self.q))

    def names(self) -> list[str]:
        return [c[0] for c in self.calls]

    # ------------------------------------------------------------ watchdog
    def feed(self) -> None:
        """An RTDE input update from the control interface (a kick or any command)."""
        now = time.monotonic()
        if self.watchdog_hz is not None and self.last_feed_s is not None:
            gap = now - self.last_feed_s
            self.feed_gaps_s.append(gap)
            if gap > 1.0 / self.watchdog_hz:
                self.watchdog_tripped = True
                if self.trip_stops_script:
                    self.program_running = False  # the control script stops; the arm with it
                    self.update(now)
                    self.move = None
        self.last_feed_s = now

    @property
    def max_feed_gap_s(self) -> float:
        return max(self.feed_gaps_s, default=0.0)

    # ------------------------------------------------------------ motion
    def update(self, now: float | None = None) -> None:
        m = self.move
        if m is None:
            return
        now = time.monotonic() if now is None else now
        if self.protective_stop_after_s is not None and now - m["t0"] >= self.protective_stop_after_s:
            # The arm freezes; the paused script's status register still reads "running".
            self.protective_stopped = True
            now = m["t0"] + self.protective_stop_after_s
        s = 1.0 if m["duration"] <= 0 else min(1.0, (now - m["t0"]) / m["duration"])
        if self.stall_moves:
            s = min(s, 0.5)
        at = [a + s * (b - a) for a, b in zip(m["from"], m["to"])]
        if m["joints"]:
            self.set_q(at)
        else:
            self.pose = at
        if s >= 1.0:
            self.move = None

    def start_move(self, pose, speed) -> float:
        """A ``moveL`` to ``pose`` at ``speed`` m/s; returns its duration."""
        d = float(np.linalg.norm(np.subtract(pose[:3], self.pose[:3])))
        return self._start(d / speed, list(self.pose), list(pose), joints=False)

    def start_joint_move(self, q, speed) -> float:
        """A ``moveJ`` to ``q`` with the leading joint at ``speed`` rad/s; returns its duration."""
        d = float(np.max(np.abs(np.subtract(q, self.q))))
        return self._start(d / speed, list(self.q), [float(x) for x in q], joints=True)

    def _start(self, duration, start, goal, joints: bool) -> float:
        self.move = {"t0": time.monotonic(), "duration": duration, "from": start, "to": goal, "joints": joints}
        self.op_id = (self.op_id + 1) % 128
        return duration


class FakeAsyncOperationStatus:
    """ur-rtde's ``AsyncOperationStatus`` (the status word of ``getAsyncOperationProgressEx``)."""

    def __init__(self, op_id: int, running: bool):
        self._id, self._running = op_id, running

    def isAsyncOperationRunning(self):
        return self._running

    def operationId(self):
        return self._id

    def progress(self):
        return 0 if self._running else -1


def make_ur_modules(ctrl: FakeURController) -> dict[str, types.ModuleType]:
    class RTDEControlInterface:
        def __init__(self, host):
            if ctrl.fail_connect or ctrl.fail_control_init:
                raise RuntimeError("Failed to connect to the robot")
            ctrl.log("control_init", host)
            self._stale = 0

        def setWatchdog(self, min_frequency=10.0):
            ctrl.log("setWatchdog", min_frequency)
            if ctrl.fail_set_watchdog:
                raise RuntimeError("RTDE control script is not running!")
            ctrl.watchdog_hz = float(min_frequency)
            ctrl.feed()
            return True

        def kickWatchdog(self):
            ctrl.log("kickWatchdog")
            ctrl.feed()
            return True

        def _move(self, name, target, speed, acceleration, asynchronous, start) -> bool:
            """``moveL``/``moveJ``: ``start(target, speed)`` begins the motion and returns its duration."""
            ctrl.log(name, list(target), speed, acceleration, asynchronous)
            ctrl.feed()
            ctrl.update()
            if ctrl.protective_stopped or not ctrl.program_running or ctrl.reject_moves:
                return False
            duration = start(list(target), speed)
            if asynchronous:
                self._stale = ctrl.stale_polls
                return True
            time.sleep(duration)  # blocking: nothing else reaches the controller meanwhile
            ctrl.update()
            return True

        def moveL(self, pose, speed=0.25, acceleration=1.2, asynchronous=False):
            return self._move("moveL", pose, speed, acceleration, asynchronous, ctrl.start_move)

        def moveJ(self, q, speed=1.05, acceleration=1.4, asynchronous=False):
            return self._move("moveJ", q, speed, acceleration, asynchronous, ctrl.start_joint_move)

        def getAsyncOperationProgressEx(self):
            ctrl.update()
            if self._stale > 0:  # the script has not started the move thread yet
                self._stale -= 1
                return FakeAsyncOperationStatus((ctrl.op_id - 1) % 128, False)
            return FakeAsyncOperationStatus(ctrl.op_id, ctrl.move is not None)

        def stopL(self, a=10.0, asynchronous=False):
            ctrl.log("stopL", a)
            ctrl.feed()
            ctrl.update()
            ctrl.move = None

        def stopJ(self, a=2.0, asynchronous=False):
            ctrl.log("stopJ", a)
            ctrl.feed()
            ctrl.update()
            ctrl.move = None

        def servoJ(self, q, speed, acceleration, time, lookahead_time, gain):
            ctrl.log("servoJ", list(q), speed, acceleration, time, lookahead_time, gain)
            ctrl.feed()
            ctrl.set_q(q)
            return True

        def servoL(self, pose, speed, acceleration, time, lookahead_time, gain):
            ctrl.log("servoL", list(pose), speed, acceleration, time, lookahead_time, gain)
            ctrl.feed()
            ctrl.pose = list(pose)
            return True

        def speedL(self, xd, acceleration=0.25, time=0.0):
            ctrl.log("speedL", list(xd), acceleration, time)
            ctrl.feed()
            ctrl.pose = [p + v * time for p, v in zip(ctrl.pose[:3], xd[:3])] + ctrl.pose[3:]
            return True

        def servoStop(self, a=10.0):
            ctrl.log("servoStop")
            ctrl.feed()

        def speedStop(self, a=10.0):
            ctrl.log("speedStop")
            ctrl.feed()

        def stopScript(self):
            ctrl.log("stopScript")
            ctrl.feed()
            ctrl.watchdog_hz = None  # no script, no watchdog

        def reuploadScript(self):
            ctrl.log("reuploadScript")
            ctrl.program_running = True
            return True

        def isProgramRunning(self):
            return ctrl.program_running

        def isConnected(self):
            return ctrl.connected

        def disconnect(self):
            ctrl.log("control_disconnect")

    class RTDEReceiveInterface:
        def __init__(self, host):
            if ctrl.fail_connect:
                raise RuntimeError("Failed to connect to the robot")
            ctrl.log("receive_init", host)

        def getActualTCPPose(self):
            ctrl.update()
            return list(ctrl.pose)

        def getActualQ(self):
            ctrl.update()
            return list(ctrl.q)

        def isProtectiveStopped(self):
            ctrl.update()
            return ctrl.protective_stopped

        def isEmergencyStopped(self):
            return ctrl.emergency_stopped

        def isConnected(self):
            return ctrl.connected

        def disconnect(self):
            ctrl.log("receive_disconnect")

    class DashboardClient:
        def __init__(self, host):
            ctrl.log("dashboard_init", host)

        def connect(self, timeout_ms=2000):
            ctrl.log("dashboard_connect")
            if ctrl.dashboard_unreachable:
                raise RuntimeError("Connection refused")

        def getRobotModel(self):
            return ctrl.robot_model

        def __getattr__(self, name):
            # Older ur-rtde releases have no getSerialNumber.
            if name == "getSerialNumber" and ctrl.serial_number is not None:
                return lambda: ctrl.serial_number
            raise AttributeError(name)

        def closeSafetyPopup(self):
            ctrl.log("closeSafetyPopup")

        def unlockProtectiveStop(self):
            ctrl.log("unlockProtectiveStop")
            ctrl.protective_stopped = False

        def disconnect(self):
            ctrl.log("dashboard_disconnect")

    if not ctrl.has_async_status:  # an ur-rtde too old for getAsyncOperationProgressEx
        del RTDEControlInterface.getAsyncOperationProgressEx
    mods = {}
    for name, attrs in {
        "rtde_control": {"RTDEControlInterface": RTDEControlInterface},
        "rtde_receive": {"RTDEReceiveInterface": RTDEReceiveInterface},
        "dashboard_client": {"DashboardClient": DashboardClient},
    }.items():
        m = types.ModuleType(name)
        for k, v in attrs.items():
            setattr(m, k, v)
        mods[name] = m
    return mods


def install_ur(monkeypatch, ctrl: FakeURController | None = None) -> FakeURController:
    ctrl = ctrl or FakeURController()
    for name, mod in make_ur_modules(ctrl).items():
        monkeypatch.setitem(__import__("sys").modules, name, mod)
    return ctrl


# ---------------------------------------------------------------------------- depthai

XLINK_MESSAGE = (
    "Communication exception - possible device error. Original message 'Couldn't read data from stream: "
    "'out' (X_LINK_ERROR)'"
)


class FakeOak:
    """Device state behind the fake depthai module."""

    def __init__(self):
        self.requested: list[tuple] = []
        self.started = False
        self.stopped = False
        self.fail_after: int | None = None  # frames before the USB link "drops"
        self.served = 0
        self.period_s = 0.002
        self.attached = True
        self.device_id = "18443010D116631200"
        self.product_name = "OAK-D-PRO-W-97"


def make_depthai(oak: FakeOak) -> types.ModuleType:
    dai = types.ModuleType("depthai")

    class CameraBoardSocket:
        CAM_A, CAM_B, CAM_C, CAM_D = "CAM_A", "CAM_B", "CAM_C", "CAM_D"

    class ImgFrame:
        class Type:
            BGR888i = "BGR888i"
            NV12 = "NV12"

    class _Msg:
        def __init__(self, bgr, seq):
            self._bgr, self._seq = bgr, seq
            self._ts = datetime.timedelta(seconds=time.monotonic() - 0.004)  # 4 ms exposure-to-host

        def getCvFrame(self):
            return self._bgr

        def getSequenceNum(self):
            return self._seq

        def getTimestamp(self):
            return self._ts

    class _Queue:
        def __init__(self, size):
            self.w, self.h = size
            self._next = time.monotonic()

        def tryGet(self):
            if oak.fail_after is not None and oak.served >= oak.fail_after:
                raise RuntimeError(XLINK_MESSAGE)
            if time.monotonic() < self._next:
                return None
            self._next = time.monotonic() + oak.period_s
            bgr = np.zeros((self.h, self.w, 3), np.uint8)
            bgr[..., 0] = 200  # blue in BGR
            msg = _Msg(bgr, oak.served)
            oak.served += 1
            return msg

    class _Output:
        def __init__(self, size):
            self.size = size

        def createOutputQueue(self, maxSize=16, blocking=True):
            oak.requested.append(("queue", maxSize, blocking))
            return _Queue(self.size)

    class _CameraNode:
        def build(self, socket):
            oak.requested.append(("build", socket))
            return self

        def requestOutput(self, size, type=None, fps=None):
            oak.requested.append(("output", tuple(size), type, fps))
            return _Output(tuple(size))

    class _Calib:
        def getCameraIntrinsics(self, socket, w, h):
            return [[0.9 * w, 0.0, w / 2.0], [0.0, 0.9 * w, h / 2.0], [0.0, 0.0, 1.0]]

        def getDistortionCoefficients(self, socket):
            return [0.01] + [0.0] * 13

        def getEepromData(self):
            return types.SimpleNamespace(productName=oak.product_name, boardName="DM9098")

    class _Device:
        def readCalibration(self):
            return _Calib()

        def getDeviceId(self):
            return oak.device_id

    class Pipeline:
        def __init__(self):
            if not oak.attached:  # depthai v3 connects to the device when the pipeline is created
                raise RuntimeError("No available devices")

        def create(self, kind):
            return kind()

        def start(self):
            oak.requested.append(("start",))
            oak.started = True

        def stop(self):
            oak.stopped = True

        def getDefaultDevice(self):
            return _Device()

    dai.Pipeline = Pipeline
    dai.CameraBoardSocket = CameraBoardSocket
    dai.ImgFrame = ImgFrame
    dai.node = types.SimpleNamespace(Camera=_CameraNode)
    return dai


def install_depthai(monkeypatch, oak: FakeOak | None = None) -> FakeOak:
    oak = oak or FakeOak()
    monkeypatch.setitem(__import__("sys").modules, "depthai", make_depthai(oak))
    return oak


# ---------------------------------------------------------------------------- cv2.VideoCapture


class FakeCaptureDevice:
    """What a UVC device supports; FakeVideoCapture instances read from it."""

    def __init__(
        self, sizes=((640, 480), (1280, 720), (320, 240)), fps=200.0, honours_fps=True, fourccs=("YUYV", "MJPG")
    ):
        self.sizes = list(sizes)
        self.fps = fps
        self.honours_fps = honours_fps
        self.fourccs = fourccs
        self.fail_after: int | None = None
        self.opened_with: list = []
        self.set_calls: list[tuple[int, float]] = []
        self.frames_read = 0
        self.released = threading.Event()


def make_video_capture(dev: FakeCaptureDevice, cv2):
    class FakeVideoCapture:
        def __init__(self, src, api=None):
            dev.opened_with.append((src, api))
            self.props = {
                cv2.CAP_PROP_FRAME_WIDTH: dev.sizes[0][0],
                cv2.CAP_PROP_FRAME_HEIGHT: dev.sizes[0][1],
                cv2.CAP_PROP_FPS: 30.0,
                cv2.CAP_PROP_BUFFERSIZE: 4.0,
                cv2.CAP_PROP_FOURCC: float(cv2.VideoWriter_fourcc(*dev.fourccs[0])),
            }
            self._open = True

        def isOpened(self):
            return self._open

        def set(self, prop, value):
            dev.set_calls.append((prop, value))
            if prop == cv2.CAP_PROP_FPS and not dev.honours_fps:
                return False
            if prop == cv2.CAP_PROP_FOURCC:
                code = "".join(chr((int(value) >> 8 * i) & 0xFF) for i in range(4))
                if code not in dev.fourccs:
                    return False
            if prop in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT):
                # Like V4L2: pick the supported size nearest to the request on this axis.
                axis = 0 if prop == cv2.CAP_PROP_FRAME_WIDTH else 1
                other = self.props[cv2.CAP_PROP_FRAME_HEIGHT if axis == 0 else cv2.CAP_PROP_FRAME_WIDTH]
                best = min(dev.sizes, key=lambda s: (abs(s[axis] - value), abs(s[1 - axis] - other)))
                self.props[cv2.CAP_PROP_FRAME_WIDTH], self.props[cv2.CAP_PROP_FRAME_HEIGHT] = best
                return True
            self.props[prop] = float(value)
            return True

        def get(self, prop):
            return float(self.props.get(prop, 0.0))

        def getBackendName(self):
            return "V4L2"

        def read(self):
            time.sleep(1.0 / dev.fps)
            if dev.fail_after is not None and dev.frames_read >= dev.fail_after:
                return False, None
            w, h = int(self.props[cv2.CAP_PROP_FRAME_WIDTH]), int(self.props[cv2.CAP_PROP_FRAME_HEIGHT])
            bgr = np.zeros((h, w, 3), np.uint8)
            bgr[..., 2] = 255  # red in BGR
            dev.frames_read += 1
            return True, bgr

        def release(self):
            self._open = False
            dev.released.set()

    return FakeVideoCapture


def install_video_capture(monkeypatch, dev: FakeCaptureDevice | None = None) -> FakeCaptureDevice:
    import cv2

    dev = dev or FakeCaptureDevice()
    monkeypatch.setattr(cv2, "VideoCapture", make_video_capture(dev, cv2))
    return dev


# ---------------------------------------------------------------------------- a pure-math arm


def make_pose(x=0.4, y=0.0, z=0.3, rotvec=(np.pi, 0.0, 0.0)) -> np.ndarray:
    return pose_from_vec([x, y, z, *rotvec])


class RecordingArm(Arm):
    """Follows every command exactly and records it: what the safety layer let through."""

    name = "recording"

    def __init__(self, T_start=None):
        super().__init__()
        self.T = make_pose() if T_start is None else np.array(T_start, dtype=np.float64)
        self.servos: list[tuple[np.ndarray, np.ndarray, float]] = []  # (T_before, T_cmd, duration_s)
        self.moves: list[tuple[np.ndarray, float]] = []
        self.stops = 0
        self.kicks = 0
        self.fault_value: Fault | None = None
        self.raise_on_servo: BaseException | None = None

    def _open(self):
        pass

    def _close(self):
        pass

    def tcp_pose(self):
        return self.T.copy()

    def move_to(self, T_base_tcp, speed_mps):
        self.moves.append((np.array(T_base_tcp), speed_mps))
        self.T = np.array(T_base_tcp, dtype=np.float64)

    def servo(self, T_base_tcp, duration_s):
        if self.raise_on_servo is not None:
            raise self.raise_on_servo
        self.servos.append((self.T.copy(), np.array(T_base_tcp), duration_s))
        self.T = np.array(T_base_tcp, dtype=np.float64)

    def stop(self):
        self.stops += 1

    def fault(self):
        return self.fault_value

    def keepalive(self):
        self.kicks += 1

    def identity(self):
        return {"serial": "recording"}
