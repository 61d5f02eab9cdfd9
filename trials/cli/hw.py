"""``advobj hw``: check the robot hardware (or its simulation) described by a hardware YAML."""

from __future__ import annotations

import contextlib
from pathlib import Path

import typer

from robot_io.errors import MissingIntrinsicsError

app = typer.Typer(no_args_is_help=True, help="Check the wrist camera and arm of a hardware config.")


@app.command()
def check(
    config: Path = typer.Option(..., "--config", "-c", help="hardware YAML (see examples/hardware/)"),
    frames: int = typer.Option(60, min=2, help="camera frames to time"),
    jog: bool = typer.Option(False, "--jog", help="also move the TCP up and back (through the safety layer)"),
    jog_mm: float = typer.Option(10.0, help="jog distance along base +z in mm"),
) -> None:
    """Connect, print the camera's measured fps and latency, the arm pose and, for an arm a URDF
    describes, its joints (value, unit, distance to each limit). Moves nothing unless --jog."""
    from robot_io.check import (  # lazy: CLI start-up (+6 ms)
        format_joint,
        format_pose,
        jog_z,
        joint_readings,
        measure_camera,
    )
    from robot_io.config import (  # lazy: CLI start-up (trimesh, PIL)
        build_arm,
        build_camera,
        build_world,
        load_hardware_config,
    )

    cfg = load_hardware_config(config)
    with contextlib.ExitStack() as stack:
        world = None
        if "sim" in (cfg.camera.type, cfg.arm.type):
            world = build_world(cfg)
            stack.callback(world.close)
        camera = build_camera(cfg, world)
        arm = build_arm(cfg, world)
        # The camera is timed before the arm connects: a connected UR arm's watchdog stops its
        # control script unless kicked every 1 / watchdog_min_hz, which timing frames would not do.
        with camera:
            s = measure_camera(camera, frames)
            typer.echo(
                f"camera ({cfg.camera.type}): {s.width}x{s.height}, {s.fps:.1f} fps over {s.frames} frames, "
                f"{s.dropped} dropped"
            )
            typer.echo(
                f"  read() {s.read_ms_median:.1f} ms median / {s.read_ms_p95:.1f} ms p95; "
                f"frame age {s.age_ms_median:.1f} ms median / {s.age_ms_p95:.1f} ms p95"
            )
            try:
                K = camera.intrinsics.K
            except MissingIntrinsicsError:  # optional: only tag-based locating needs them
                typer.echo("  intrinsics: not configured")
            else:
                typer.echo(f"  intrinsics fx={K[0, 0]:.1f} fy={K[1, 1]:.1f} cx={K[0, 2]:.1f} cy={K[1, 2]:.1f} px")
        with arm:
            arm.keepalive()
            fault = arm.fault()
            typer.echo(f"arm ({cfg.arm.type}): {format_pose(arm.tcp_pose())}")
            typer.echo(f"  fault: {fault if fault else 'none'}")
            inside = cfg.safety.contains(arm.tcp_pose()[:3, 3])
            typer.echo(f"  TCP {'inside' if inside else 'OUTSIDE'} the safety workspace box")
            kin = arm.kinematics()
            if kin is not None:
                # Where each joint reads, against where the arm stands, shows a servo's sign and
                # offset_ticks (or a wrong URDF) before any joint command is sent.
                readings = joint_readings(kin, arm.joint_positions())
                typer.echo(f"  joints ({kin.n_joints}, in the URDF's order and units):")
                width = max(len(r.name) for r in readings)
                for reading in readings:
                    typer.echo(f"    {format_joint(reading, width)}")
                outside = [r.name for r in readings if not r.inside]
                if outside:
                    typer.echo(
                        f"  {', '.join(outside)} OUTSIDE the URDF's limits: check the joint's sign and offset_ticks "
                        "(servo-bus arms) or the URDF"
                    )
            if jog:
                T0, T1, T2 = jog_z(arm, jog_mm / 1000.0)
                typer.echo(f"jog: up to {format_pose(T1)}")
                typer.echo(f"     back to {format_pose(T2)}")
            else:
                typer.echo("nothing moved (use --jog to move the TCP)")


@app.command("serial-sim")
def serial_sim(
    boot_delay_ms: float = typer.Option(1000.0, min=0.0, max=60000.0, help="time to the boot banner, 0-60000 ms"),
) -> None:
    """Run the serial arm simulator on a pseudo-terminal and print its port (Ctrl-C to stop)."""
    from robot_io.arms.pty_twin import serve_until_interrupted  # lazy: CLI start-up (robot_io.arms)
    from robot_io.arms.serial_sim import SerialArmSimulator  # lazy: CLI start-up (+16 ms)

    sim, path = SerialArmSimulator.on_pty(boot_delay_s=boot_delay_ms / 1000.0)
    serve_until_interrupted(sim, f"serial arm simulator on {path}; set arm.port to it", say=typer.echo)
