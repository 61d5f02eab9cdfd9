"""Universal Robots arms through ur-rtde (``pip install 'advobj[ur]'``).

* ``moveL`` positions; the policy loop streams ``servoL`` (or ``speedL``) targets.
* ``setWatchdog`` makes the controller stop the arm when our process stops kicking it, so a
  crashed or frozen Python process cannot leave the arm following its last command. From
  ``connect()`` on, something must reach the controller at least every ``1 / watchdog_min_hz``:
  the policy loop's commands, or :meth:`URArm.keepalive`. ``moveL`` therefore runs
  asynchronously and :meth:`URArm.move_to` kicks the watchdog (and checks for faults) while it
  polls ``getAsyncOperationProgressEx`` for the end of the move; a blocking ``moveL`` longer than
  the watchdog period would stop the control script mid-move.
* Given ``kinematics`` (the UR's :class:`sim.ik.SceneArm`), the arm also takes joint commands:
  :meth:`URArm.joint_positions` reads ``getActualQ``, :meth:`URArm.servo_joints` streams ``servoJ``
  and :meth:`URArm.move_joints` runs an asynchronous ``moveJ`` waited for like ``moveL`` (watchdog
  kicked, faults checked, a timeout, ``stopJ`` when interrupted).
  Connecting refuses, in one line and before anything moves, an arm whose ``getActualQ`` puts the
  TCP, through the kinematics' FK, farther from ``getActualTCPPose`` than 5 mm or 0.02 rad
  (:func:`robot_io.arms.base.check_kinematics_agree`: a wrong URDF, base placement or TCP offset).
* A ``moveL``/``moveJ`` the controller rejects while no fault is raised (a target it cannot
  reach) is an :class:`~robot_io.errors.ArmRefusedError`: nothing moved, the arm takes the next
  command.
* A protective stop, an e-stop, a stopped control script or a dropped link becomes an
  :class:`ArmFaultError` that says what happened and how to recover (via ``DashboardClient``).
* ``disconnect`` always runs ``servoStop``/``speedStop`` (both after ``servoJ`` in ``speedL`` mode)
  -> ``stopScript`` -> ``disconnect``,
  each step in a ``finally`` so one failing call cannot skip the next.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Literal

import numpy as np

from robot_io.arms.base import Arm, Fault, check_joint_target, check_kinematics_agree
from robot_io.errors import ArmFaultError, ArmRefusedError, MissingExtraError, RobotIOError, require_extra
from robot_io.poses import pose_from_vec, pose_step, pose_to_vec
from sim.geometry import so3_log

if TYPE_CHECKING:
    from sim.ik import SceneArm

__all__ = ["URArm", "PROTECTIVE_STOP_RECOVERY", "UR_JOINTS", "joint_move_speed_radps"]

log = logging.getLogger(__name__)

# moveL timeout: twice the trapezoid's duration plus this margin (controller start-up, slow
# rotation-dominated moves at _MOVE_ROT_RADPS); a move still running then is stopped as a fault.
_MOVE_MARGIN_S = 2.0
_MOVE_ROT_RADPS = 0.5
_STOP_DECEL_MPS2 = 10.0  # ur-rtde's stopL default
_STOP_DECEL_RADPS2 = 2.0  # ur-rtde's stopJ default (leading joint)
_MIN_JOINT_SPEED_RADPS = 1e-3  # moveJ speed of a move that goes nowhere (ur-rtde refuses 0)
#: Joints of every UR arm (base, shoulder, elbow, wrist 1-3).
UR_JOINTS = 6

PROTECTIVE_STOP_RECOVERY = (
    "check the cause on the teach pendant (collision, joint limit), clear the workspace, then "
    "unlock the protective stop (URArm.recover() calls DashboardClient.unlockProtectiveStop and "
    "RTDEControlInterface.reuploadScript) and reconnect"
)


def joint_move_speed_radps(distance_rad: float, duration_s: float) -> float:
    """The ``moveJ`` speed (leading joint, rad/s) for a move of ``distance_rad`` (the largest joint
    change) to take about ``duration_s``: the mean speed ``distance_rad / duration_s``.

    Never faster: the caller's ``duration_s`` comes from a speed cap (:meth:`robot_io.safety.SafeArm.move_joints`),
    so the leading joint cruises at that cap and the trapezoid's ramps make the move take
    ``speed / acceleration`` longer than ``duration_s``. A move of zero distance gets a small speed
    (ur-rtde refuses 0); a move no finite speed makes in ``duration_s`` (zero time, overflow) is a
    :class:`RobotIOError`.
    """
    if not (np.isfinite(distance_rad) and distance_rad >= 0 and np.isfinite(duration_s) and duration_s >= 0):
        raise RobotIOError(
            f"joint move: distance_rad and duration_s must be finite and >= 0, got {distance_rad} and {duration_s}"
        )
    if distance_rad == 0:
        return _MIN_JOINT_SPEED_RADPS
    with np.errstate(over="ignore"):
        v = distance_rad / duration_s if duration_s > 0 else np.inf
    if not np.isfinite(v):
        raise RobotIOError(f"joint move: {distance_rad:.4g} rad in {duration_s:.4g} s is no finite speed")
    return max(v, _MIN_JOINT_SPEED_RADPS)


class URArm(Arm):
    """A UR e-Series / CB3 arm.

    Args:
        host: controller address (from the hardware config).
        mode: ``servoL`` (position streaming) or ``speedL`` (velocity streaming) for :meth:`servo`.
        acceleration_mps2: Cartesian acceleration for ``moveL`` / ``speedL``.
        lookahead_time_s, gain: ``servoL`` smoothing (UR ranges 0.03-0.2 s and 100-2000).
        watchdog_min_hz: the controller stops the arm if not kicked at least this often.
        kinematics: the arm's :class:`sim.ik.SceneArm` (a UR URDF chain, 6 joints; its TCP in the
            frame of ``getActualTCPPose``): given, the arm takes joint commands (``servoJ``,
            ``moveJ``); ``None``, TCP commands only.
        joint_acceleration_radps2: ``moveJ`` acceleration of the leading joint.
    """

    name = "ur_rtde"

    def __init__(
        self,
        host: str,
        mode: Literal["servoL", "speedL"] = "servoL",
        acceleration_mps2: float = 0.5,
        lookahead_time_s: float = 0.1,
        gain: float = 300.0,
        watchdog_min_hz: float = 10.0,
        *,
        kinematics: SceneArm | None = None,
        joint_acceleration_radps2: float = 1.4,
    ):
        super().__init__()
        if mode not in ("servoL", "speedL"):
            raise ValueError(f"mode must be 'servoL' or 'speedL', got {mode!r}")
        self.host = host
        self.mode = mode
        self.acceleration_mps2 = float(acceleration_mps2)
        self.lookahead_time_s = float(lookahead_time_s)
        self.gain = float(gain)
        self.watchdog_min_hz = float(watchdog_min_hz)
        self._kinematics = kinematics
        self.joint_acceleration_radps2 = float(joint_acceleration_radps2)
        # The stop calls that end what was streamed: servoL/servoJ -> servoStop, speedL -> speedStop.
        self._stream_stops = {"servoStop" if mode == "servoL" else "speedStop"}
        self._rtde_c = None
        self._rtde_r = None
        self._dashboard_mod = None
        self._controller: dict[str, str] = {}  # serial number and model, read from the dashboard on connect

    # ------------------------------------------------------------------ connection
    def _open(self) -> None:
        kin = self._kinematics
        if kin is not None and kin.n_joints != UR_JOINTS:
            raise RobotIOError(
                f"UR {self.host}: the arm's URDF chain has {kin.n_joints} joints ({', '.join(kin.joint_names)}); "
                f"a UR arm has {UR_JOINTS}: give the UR's URDF (e.g. the shipped 'ur5')"
            )
        rtde_control = require_extra("rtde_control", "ur", "the UR arm driver")
        rtde_receive = require_extra("rtde_receive", "ur", "the UR arm driver")
        self._dashboard_mod = require_extra("dashboard_client", "ur", "the UR arm driver")
        if not hasattr(rtde_control.RTDEControlInterface, "getAsyncOperationProgressEx"):
            raise MissingExtraError(
                "the installed ur-rtde has no RTDEControlInterface.getAsyncOperationProgressEx, "
                "which the UR driver needs to wait for moveL: pip install -U ur-rtde"
            )
        try:
            self._rtde_r = rtde_receive.RTDEReceiveInterface(self.host)
            self._rtde_c = rtde_control.RTDEControlInterface(self.host)
            self._controller = self._read_controller_identity()  # before the watchdog runs
            if kin is not None:
                self._check_kinematics()  # before the watchdog runs: an FK is no kick
            self._rtde_c.setWatchdog(self.watchdog_min_hz)
        except BaseException as err:
            # Release what was opened: a dangling receive interface keeps its RTDE thread running,
            # a control interface its script on the controller.
            self._close_quietly()
            if isinstance(err, RuntimeError):
                raise ArmFaultError(
                    Fault(
                        "connection_lost",
                        f"cannot connect to UR controller at {self.host}: {err}",
                        "check the network, that the arm is powered on and in remote control",
                    )
                ) from None
            raise

    def _read_controller_identity(self) -> dict[str, str]:
        # The serial number is for the session record only: not being able to read it is no error.
        out: dict[str, str] = {}
        try:
            dash = self._dashboard_mod.DashboardClient(self.host)
            dash.connect()
            try:
                for key, getter in (("serial", "getSerialNumber"), ("model", "getRobotModel")):
                    fn = getattr(dash, getter, None)  # getSerialNumber is missing in older ur-rtde releases
                    if fn is not None:
                        out[key] = str(fn()).strip()
            finally:
                dash.disconnect()
        except Exception as err:  # noqa: BLE001
            log.warning(
                "UR %s: cannot read the controller's serial number from the dashboard server (%s)", self.host, err
            )
        return out

    def _check_kinematics(self) -> None:
        """Refuse to connect (:func:`robot_io.arms.base.check_kinematics_agree`, one line) when the FK of
        ``getActualQ`` is not the ``getActualTCPPose`` the controller computes: a wrong URDF, base
        placement or TCP, on which the safety layer would check the workspace box. Nothing has moved."""
        check_kinematics_agree(
            f"UR {self.host}",
            self._kinematics,
            self.joint_positions(),
            self.tcp_pose(),
            hint="a UR's base is ur_description's base_link turned by pi about z (rotvec_base_link [0, 0, "
            "3.141592653589793]), its TCP the pendant's TCP offset; a URDF without the arm's factory "
            "calibration can be centimetres off on some arms (UR's ur_calibration corrects it)",
        )

    def identity(self) -> dict[str, str]:
        return {"host": self.host, **self._controller}

    def _close_quietly(self) -> None:
        try:
            self._close()
        except Exception as err:  # noqa: BLE001 - on an error path: the original error matters more
            log.warning("UR %s: releasing the RTDE interfaces failed (%s)", self.host, err)

    def _close(self) -> None:
        c, r = self._rtde_c, self._rtde_r
        self._rtde_c = self._rtde_r = None
        try:
            if c is not None:
                try:
                    self._stop_streams(c)
                finally:
                    try:
                        c.stopScript()
                    finally:
                        c.disconnect()
        finally:
            if r is not None:
                r.disconnect()

    # ------------------------------------------------------------------ state
    def fault(self) -> Fault | None:
        c, r = self._rtde_c, self._rtde_r
        if c is None or r is None:
            return Fault("connection_lost", "not connected to the UR controller", "call connect()")
        if not (r.isConnected() and c.isConnected()):
            return Fault(
                "connection_lost",
                f"RTDE connection to {self.host} lost",
                "check the network cable, then reconnect (the watchdog has stopped the arm)",
            )
        if r.isEmergencyStopped():
            return Fault(
                "emergency_stop",
                "the emergency stop is pressed",
                "release the e-stop, re-enable the arm on the teach pendant, then reconnect",
            )
        if r.isProtectiveStopped():
            return Fault("protective_stop", "the controller raised a protective stop", PROTECTIVE_STOP_RECOVERY)
        if not c.isProgramRunning():
            return Fault(
                "program_stopped",
                "the RTDE control script is not running",
                "reconnect, or call URArm.recover() to re-upload the control script",
            )
        return None

    def _require_ok(self) -> None:
        f = self.fault()
        if f is not None:
            raise ArmFaultError(f)

    def tcp_pose(self) -> np.ndarray:
        if self._rtde_r is None:
            raise ArmFaultError(Fault("connection_lost", "not connected to the UR controller", "call connect()"))
        return pose_from_vec(self._rtde_r.getActualTCPPose())

    # ------------------------------------------------------------------ motion
    def keepalive(self) -> None:
        if self._rtde_c is not None:
            self._rtde_c.kickWatchdog()

    def move_to(self, T_base_tcp: np.ndarray, speed_mps: float, timeout_s: float | None = None) -> None:
        """``moveL`` there, kicking the watchdog and checking faults until the move has ended.

        ``timeout_s`` (default: from distance, speed and acceleration, with a margin): a move
        still running then is stopped and raised as a fault.
        """
        self.keepalive()
        self._require_ok()
        T_goal = np.asarray(T_base_tcp, dtype=np.float64)
        v = float(speed_mps)
        if timeout_s is None:
            dp, dr = pose_step(self.tcp_pose(), T_goal)
            timeout_s = 2.0 * (dp / v + v / self.acceleration_mps2 + dr / _MOVE_ROT_RADPS) + _MOVE_MARGIN_S
        self._run_async_move(
            "moveL",
            lambda c: c.moveL(pose_to_vec(T_goal), v, self.acceleration_mps2, True),
            timeout_s,
            lambda c: c.stopL(_STOP_DECEL_MPS2),
        )

    def _run_async_move(
        self, what: str, start: Callable[[object], bool], timeout_s: float, stop: Callable[[object], None]
    ) -> None:
        """Start an asynchronous move (``start(control_interface)``) and wait for its end, kicking the
        watchdog and checking faults; on a fault, the timeout or Ctrl-C the move is ended by ``stop``."""
        c = self._rtde_c
        # The operation id changes when the controller starts our move; until then the status
        # register may still show the previous (finished) operation.
        before = c.getAsyncOperationProgressEx().operationId()
        poll_s = min(0.01, 0.25 / self.watchdog_min_hz)
        try:
            if not start(c):
                self._require_ok()  # a refused move is usually a fault raised meanwhile
                # No fault: the controller will not execute this target (out of reach, past a joint limit).
                raise ArmRefusedError(
                    f"UR {self.host}: the controller rejected the {what} with no fault raised (a target it cannot "
                    "reach; see the teach pendant log); the arm did not move"
                )
            deadline = time.monotonic() + timeout_s
            while True:
                self.keepalive()
                self._require_ok()
                st = c.getAsyncOperationProgressEx()
                if st.operationId() != before and not st.isAsyncOperationRunning():
                    self._require_ok()  # ended by a fault raised since the check above?
                    return
                if time.monotonic() > deadline:
                    raise ArmFaultError(
                        Fault(
                            "device_fault",
                            f"{what} did not finish within {timeout_s:.1f} s",
                            "check the teach pendant for what held the arm back",
                        )
                    )
                time.sleep(poll_s)
        except BaseException:
            # Fault, timeout, Ctrl-C: an asynchronous move keeps going unless stopped (servoStop does not).
            try:
                stop(c)
            except Exception as err:  # noqa: BLE001 - a faulted controller may refuse; the error raised matters more
                log.warning("UR %s: stopping the interrupted %s failed (%s)", self.host, what, err)
            raise

    def servo(self, T_base_tcp: np.ndarray, duration_s: float) -> None:
        # Kick first: even if this step raises, the controller knows we were alive just now.
        self.keepalive()
        self._require_ok()
        if self.mode == "servoL":
            # ur-rtde ignores servoL's speed and acceleration arguments; time is the step period.
            self._rtde_c.servoL(pose_to_vec(T_base_tcp), 0.0, 0.0, float(duration_s), self.lookahead_time_s, self.gain)
        else:
            T_now = self.tcp_pose()
            T_goal = np.asarray(T_base_tcp, dtype=np.float64)
            v = (T_goal[:3, 3] - T_now[:3, 3]) / duration_s
            # Angular velocity in the base frame: the rotation R_goal R_now^T, as axis-angle per second.

            w = so3_log(T_goal[:3, :3] @ T_now[:3, :3].T) / duration_s
            self._rtde_c.speedL([float(x) for x in np.concatenate([v, w])], self.acceleration_mps2, float(duration_s))

    def stop(self) -> None:
        if self._rtde_c is not None:
            self._stop_streams(self._rtde_c)

    def _stop_streams(self, c) -> None:
        """``servoStop`` and/or ``speedStop``: whatever ends what this session streamed; each is tried
        even when another fails, and the first failure is raised after."""
        first: Exception | None = None
        for name in sorted(self._stream_stops):
            try:
                getattr(c, name)()
            except Exception as err:  # noqa: BLE001 - re-raised below once every stop was tried
                first = first or err
        if first is not None:
            raise first

    # ------------------------------------------------------------------ joints
    def kinematics(self) -> SceneArm | None:
        return self._kinematics

    def joint_positions(self) -> np.ndarray:
        """``getActualQ`` (rad), in the order of the kinematics' joints."""
        if self._kinematics is None:
            return super().joint_positions()  # raises: no joint commands
        if self._rtde_r is None:
            raise ArmFaultError(Fault("connection_lost", "not connected to the UR controller", "call connect()"))
        q = np.asarray(self._rtde_r.getActualQ(), dtype=np.float64)
        n = self._kinematics.n_joints
        if q.shape != (n,):
            raise RobotIOError(f"UR {self.host}: getActualQ returned {q.size} values, the arm's URDF has {n} joints")
        return q

    def servo_joints(self, q: np.ndarray, duration_s: float) -> None:
        """Stream one ``servoJ`` target, reached over ``duration_s`` (the step period)."""
        self.keepalive()  # first: even if this step raises, the controller knows we were alive just now
        q = check_joint_target(f"UR {self.host}", self._kinematics, q)
        self._require_ok()
        self._stream_stops.add("servoStop")
        # ur-rtde ignores servoJ's speed and acceleration arguments; time is the step period.
        self._rtde_c.servoJ([float(x) for x in q], 0.0, 0.0, float(duration_s), self.lookahead_time_s, self.gain)

    def move_joints(self, q: np.ndarray, duration_s: float, timeout_s: float | None = None) -> None:
        """``moveJ`` to ``q`` with the leading joint at :func:`joint_move_speed_radps`, waited for like
        :meth:`move_to`. ``timeout_s`` (default: twice the move's time with its ramps, plus a margin):
        a move still running then is stopped (``stopJ``) and raised as a fault."""
        self.keepalive()
        q = check_joint_target(f"UR {self.host}", self._kinematics, q)
        self._require_ok()
        distance = float(np.max(np.abs(q - self.joint_positions())))
        v = joint_move_speed_radps(distance, float(duration_s))
        if timeout_s is None:
            timeout_s = 2.0 * (distance / v + v / self.joint_acceleration_radps2) + _MOVE_MARGIN_S
        self._run_async_move(
            "moveJ",
            lambda c: c.moveJ([float(x) for x in q], v, self.joint_acceleration_radps2, True),
            timeout_s,
            lambda c: c.stopJ(_STOP_DECEL_RADPS2),
        )

    # ------------------------------------------------------------------ recovery
    def recover(self) -> None:
        """Unlock a protective stop and restart the control script (after the cause is removed)."""
        mod = self._dashboard_mod or require_extra("dashboard_client", "ur", "the UR arm driver")
        dash = mod.DashboardClient(self.host)
        dash.connect()
        try:
            dash.closeSafetyPopup()
            dash.unlockProtectiveStop()
        finally:
            dash.disconnect()
        if self._rtde_c is not None:
            self._rtde_c.reuploadScript()
            self._rtde_c.setWatchdog(self.watchdog_min_hz)
        log.info("UR %s: protective stop unlocked and control script re-uploaded", self.host)
