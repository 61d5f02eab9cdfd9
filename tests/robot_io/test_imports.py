"""Importing robot_io (and every driver module) loads no vendor SDK, cv2, depthai or torch."""

from __future__ import annotations

import subprocess
import sys


def test_importing_robot_io_loads_neither_cv2_nor_depthai_nor_vendor_sdks_nor_torch():
    code = (
        "import sys\n"
        "import robot_io, robot_io.config, robot_io.safety, robot_io.check, robot_io.poses\n"
        "import robot_io.cameras.opencv, robot_io.cameras.depthai, robot_io.cameras.sim, robot_io.cameras.replay\n"
        "import robot_io.arms.ur_rtde, robot_io.arms.serial, robot_io.arms.sim, robot_io.arms.serial_sim\n"
        "import robot_io.arms.servo_bus, robot_io.arms.feetech, robot_io.arms.feetech_sim\n"
        "import robot_io.arms.dynamixel, robot_io.arms.dynamixel_sim, robot_io.arms.pty_twin\n"
        "bad = [m for m in ('cv2', 'depthai', 'rtde_control', 'rtde_receive', 'dashboard_client', 'pyrender', 'serial',"
        " 'torch') if m in sys.modules]\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", f"imported eagerly: {out.stdout.strip()}"
