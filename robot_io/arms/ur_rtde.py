"""Universal Robots arms through ur-rtde (``pip install 'advobj[ur]'``).

* ``moveL`` positions; the policy loop streams ``servoL`` (or ``speedL``) targets.
* ``setWatchdog`` makes the controller stop the arm when our process stops kicking it, so a
  crashed or frozen Python process cannot leave the arm following its last command. From
  ``connect()`` on, something must reach the controller at least every ``1 / watchdog_min_hz``:
  the policy loop's commands, or :meth:`URArm.keepalive`. ``moveL`` therefore runs
  asynchronously and :meth:`URArm.move_to` kicks the watchdog (and checks for faults) while it
  polls ``getAsyncOperationProgressEx`` for the end of the move; a blocking ``moveL`` longer than
  the watchdog period would stop the control script mid-move.
* A protective stop, an e-stop, a stopped control script or a dropped link becomes an
  :class:`ArmFaultError` that says what happened and how to recover (via ``DashboardClient``).
* ``disconnect`` always runs ``servoStop``/``speedStop`` -> ``stopScript`` -> ``disconnect``,
  each step in a ``finally`` so one failing call cannot skip the next.
"""

from __future__ import annotations

import logging
import time
from typing import Literal

import numpy as np

from robot_io.arms.base import Arm, Fault
from robot_io.errors import ArmFaultError, MissingExtraError, require_extra
from robot_io.poses import pose_from_vec, pose_step, pose_to_vec
from sim.geometry import so3_log

__all__ = ["URArm", "PROTECTIVE_STOP_RECOVERY"]

log = logging.getLogger(__name__)

# moveL timeout: twice the trapezoid's duration plus this margin (controller start-up, slow
# rotation-dominated moves at _MOVE_ROT_RADPS); a move still running then is stopped as a fault.
_MOVE_MARGIN_S = 2.0
_MOVE_ROT_RADPS = 0.5
_STOP_DECEL_MPS2 = 10.0  # ur-rtde's stopL default

PROTECTIVE_STOP_RECOVERY = (
    "check the cause on the teach pendant (collision, joint limit), clear the workspace, then "
    "unlock the protective stop (URArm.recover() calls DashboardClient.unlockProtectiveStop and "
    "RTDEControlInterface.reuploadScript) and reconnect"
)


class URArm(Arm):
    """A UR e-Series / CB3 arm.

    Args:
        host: controller address (from the hardware config).
        mode: ``servoL`` (position streaming) or ``speedL`` (velocity streaming) for :meth:`servo`.
        acceleration_mps2: Cartesian acceleration for ``moveL`` / ``speedL``.
        lookahead_time_s, gain: ``servoL`` smoothing (UR ranges 0.03-0.2 s and 100-2000).
        watchdog_min_hz: the controller stops the arm if not kicked at least this often.
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
        self._rtde_c = None
        self._rtde_r = None
        self._dashboard_mod = None
        self._controller: dict[str, str] = {}  # serial number and model, read from the dashboard on connect

    # ------------------------------------------------------------------ connection
    def _open(self) -> None:
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
                    c.servoStop() if self.mode == "servoL" else c.speedStop()
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
        c = self._rtde_c
        T_goal = np.asarray(T_base_tcp, dtype=np.float64)
        v = float(speed_mps)
        if timeout_s is None:
            dp, dr = pose_step(self.tcp_pose(), T_goal)
            timeout_s = 2.0 * (dp / v + v / self.acceleration_mps2 + dr / _MOVE_ROT_RADPS) + _MOVE_MARGIN_S
        # The operation id changes when the controller starts our move; until then the status
        # register may still show the previous (finished) operation.
        before = c.getAsyncOperationProgressEx().operationId()
        poll_s = min(0.01, 0.25 / self.watchdog_min_hz)
        try:
            if not c.moveL(pose_to_vec(T_goal), v, self.acceleration_mps2, True):
                self._require_ok()  # a refused move is usually a fault raised meanwhile
                raise ArmFaultError(
                    Fault(
                        "device_fault",
                        "moveL was rejected by the controller",
                        "check the target is reachable and the teach pendant log",
                    )
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
                            f"moveL did not finish within {timeout_s:.1f} s",
                            "check the teach pendant for what held the arm back",
                        )
                    )
                time.sleep(poll_s)
        except BaseException:
            # Fault, timeout, Ctrl-C: an asynchronous move keeps going unless stopped (servoStop does not).
            try:
                c.stopL(_STOP_DECEL_MPS2)
            except Exception as err:  # noqa: BLE001 - a faulted controller may refuse; the error raised matters more
                log.warning("UR %s: stopL after an interrupted move failed (%s)", self.host, err)
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
            if self.mode == "servoL":
                self._rtde_c.servoStop()
            else:
                self._rtde_c.speedStop()

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
