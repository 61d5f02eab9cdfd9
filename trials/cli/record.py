"""``advobj record``: recordings (frames and poses) as input: import a trial session or a LeRobot dataset, or
record clean episodes in the simulator."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from trials.cli.options import int_list, key_values

app = typer.Typer(
    no_args_is_help=True,
    help="Recordings as input: frames and poses from your trial sessions, LeRobot datasets or the simulator.",
)


@app.command("import")
def import_command(
    source: str = typer.Option(
        ..., "--from", help="session (SRC: this project's trial database) or lerobot (SRC: a LeRobot dataset folder)"
    ),
    src: Path = typer.Argument(..., help="the trial database (trials.sqlite) or the LeRobot dataset's folder"),
    out: Path = typer.Option(..., help="the recording's folder (new or empty); nothing is written elsewhere"),
    session: Optional[str] = typer.Option(None, help="the session to import (--from session; default: the only one)"),
    intrinsics: List[str] = typer.Option(
        [], help="CAMERA=FILE: the camera's intrinsics YAML (repeatable); a session's own file by default"
    ),
    extrinsics: List[str] = typer.Option(
        [],
        help="CAMERA=FILE: the hand-eye result (T_tcp_cam: a wrist camera) or a T_table_cam YAML (a fixed camera); "
        "repeatable; a session's own file by default",
    ),
    table_frame: Optional[Path] = typer.Option(
        None, help="YAML with T_base_table (needed for LeRobot; a session's stored one by default)"
    ),
    camera: List[str] = typer.Option([], help="LeRobot camera to import (name or video key; repeatable; default all)"),
    episodes: Optional[str] = typer.Option(None, help="LeRobot episode indices, e.g. 0,1,2 (default all)"),
    pose_key: Optional[str] = typer.Option(None, help="LeRobot column holding the end-effector pose"),
    pose_layout: Optional[str] = typer.Option(
        None, help="xyz_rotvec, xyz_quat_xyzw or xyz_quat_wxyz (metres; joints: not read yet)"
    ),
    pose_start: int = typer.Option(0, help="index in the pose column's vector where the pose starts"),
    gripper_key: Optional[str] = typer.Option(None, help="LeRobot column holding the gripper's value"),
    gripper_index: Optional[int] = typer.Option(None, help="element of that column's vector"),
    tolerance_s: Optional[float] = typer.Option(
        None, help="how far a frame may be from its pose in time (LeRobot: 1e-4 s; a session: one control period)"
    ),
) -> None:
    """Read a trial session or a LeRobot dataset into one recording (frames, TCP poses, calibrated cameras)."""
    from trials.recordings.importer import ImportJob, run_import  # lazy: CLI start-up (numpy, pyarrow, av)

    job = ImportJob(
        source=source,
        src=src,
        out=out,
        session=session,
        intrinsics=key_values(intrinsics, "--intrinsics", "CAMERA", "FILE"),
        extrinsics=key_values(extrinsics, "--extrinsics", "CAMERA", "FILE"),
        table_frame=table_frame,
        cameras=tuple(camera),
        episodes=int_list(episodes, "--episodes"),
        pose_key=pose_key,
        pose_layout=pose_layout,
        pose_start=pose_start,
        gripper_key=gripper_key,
        gripper_index=gripper_index,
        tolerance_s=tolerance_s,
    )
    rec = run_import(job, log=typer.echo)
    frames = sum(e.n_frames for e in rec.episodes)
    typer.echo(
        f"recording: {len(rec.episodes)} episodes, {frames} steps, cameras {', '.join(rec.cameras)} in {rec.path}"
    )


@app.command("sim")
def sim_command(
    policy: Path = typer.Option(..., help="the policy that acts: a checkpoint directory, a .pt2 or an .onnx file"),
    episodes: int = typer.Option(..., help="episodes to record (configurations of the split's attack part)"),
    out: Path = typer.Option(..., help="the recording's folder (new or empty); nothing is written elsewhere"),
    scene: Optional[Path] = typer.Option(None, help="scene YAML (default: the built-in scene)"),
    seed: int = typer.Option(0, help="first configuration seed drawn (attack-part seeds from it on)"),
    max_steps: Optional[int] = typer.Option(None, help="steps per episode (default: the scene's max_steps)"),
    num_envs: int = typer.Option(8, help="episodes rolled out at once"),
    cell: str = typer.Option(
        "nominal", help="nominal: the scene as it is; shifted: the scene under another light, on another table"
    ),
    device: str = typer.Option("cpu", help="torch device of the policy"),
) -> None:
    """Record clean episodes of a policy in the simulator (the adversarial object hidden) as a recording."""
    from trials.recordings.simulated import SimRecordJob, run_record_sim  # lazy: CLI start-up (torch, pyrender)

    job = SimRecordJob(
        policy=policy,
        episodes=episodes,
        out=out,
        scene=scene,
        seed=seed,
        max_steps=max_steps,
        num_envs=num_envs,
        cell=cell,
        device=device,
    )
    rec = run_record_sim(job, log=typer.echo, progress=True)
    frames = sum(e.n_frames for e in rec.episodes)
    typer.echo(
        f"recording: {len(rec.episodes)} episodes, {frames} steps, cameras {', '.join(rec.cameras)} in {rec.path}"
    )
