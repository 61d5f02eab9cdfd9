"""sim.kinematics: URDF arms and their forward kinematics in torch.

The reference is pinocchio (``pin``): its own C++ URDF parser (urdfdom) and its own FK, sharing no
code with yourdfpy or our torch chain. Every shipped arm is checked on 10,000 random joint vectors
within its limits, plus the limits' corners, in float64: position <= 1e-6 m and rotation <= 1e-6 rad
(geodesic angle).
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import os
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import torch
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sim.kinematics import (
    JOINT_UNITS,
    MAX_URDF_BYTES,
    PROVENANCE_JSON,
    SHIPPED_ARMS,
    ArmModel,
    KinematicsError,
    load_arm,
    read_chain,
    read_provenance,
    shipped_arm,
    shipped_urdf,
    urdf_source,
)
from sim.spec import ArmModelConfig, SpecError, default_scene, load_scene, scene_from_dict

ARMS = sorted(SHIPPED_ARMS)
N_RANDOM = 10_000
TOL_POS_M = 1e-6
TOL_ROT_RAD = 1e-6
DEVICES = [
    "cpu",
    pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device here")),
]


def geodesic_angle(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Angle (rad) of ``R_a^T R_b`` for ``(..., 3, 3)``: atan2 of the sine and cosine parts, which
    stays accurate near 0 (``arccos`` of the trace cannot resolve angles below ~1e-8 rad)."""
    R = np.swapaxes(R_a, -1, -2) @ R_b
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    return np.arctan2(np.linalg.norm(v, axis=-1) / 2, (np.trace(R, axis1=-2, axis2=-1) - 1) / 2)


@functools.cache
def _pin_model(name: str):
    model = pin.buildModelFromUrdf(str(shipped_urdf(name)))
    base_link, tool_link = SHIPPED_ARMS[name]
    return model, model.getFrameId(base_link), model.getFrameId(tool_link)


def pin_T_base_tool(name: str, joint_names: tuple[str, ...], q: np.ndarray) -> np.ndarray:
    """``(B, 4, 4)`` T_base_tool by pinocchio of ``q: (B, n)`` ordered as ``joint_names``; every
    joint of the model outside the chain stays at its neutral position."""
    model, f_base, f_tool = _pin_model(name)
    data = model.createData()
    idx_q = [model.joints[model.getJointId(j)].idx_q for j in joint_names]
    out = np.empty((len(q), 4, 4))
    for i, qi in enumerate(np.asarray(q, dtype=np.float64)):
        full = pin.neutral(model)
        full[idx_q] = qi
        pin.framesForwardKinematics(model, data, full)
        out[i] = (data.oMf[f_base].inverse() * data.oMf[f_tool]).homogeneous
    return out


def _errors(T: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    pos = np.linalg.norm(T[..., :3, 3] - ref[..., :3, 3], axis=-1)
    return float(pos.max()), float(geodesic_angle(T[..., :3, :3], ref[..., :3, :3]).max())


def _within_limits(arm: ArmModel, n: int, seed: int, dtype=torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n, arm.n_joints, generator=g, dtype=torch.float64)
    q = arm.limits.q_min.cpu() + (arm.limits.q_max.cpu() - arm.limits.q_min.cpu()) * u
    return q.to(dtype)


def _corners(arm: ArmModel) -> torch.Tensor:
    """Every joint at its lower limit, at its upper limit, and alternating between the two."""
    lo, hi = arm.limits.q_min.cpu(), arm.limits.q_max.cpu()
    alt = torch.where(torch.arange(arm.n_joints) % 2 == 0, lo, hi)
    return torch.stack([lo, hi, alt, torch.where(torch.arange(arm.n_joints) % 2 == 1, lo, hi)])


@functools.cache
def _arm(name: str) -> ArmModel:
    return shipped_arm(name)


# ---------------------------------------------------------------------------------------------
# Against pinocchio


@pytest.mark.parametrize("name", ARMS)
def test_fk_matches_pinocchio_on_10000_random_joint_vectors_and_the_limit_corners(name):
    arm = _arm(name)
    q = torch.cat([_within_limits(arm, N_RANDOM, seed=31), _corners(arm)])
    T = arm.fk(q)
    assert T.dtype == torch.float64 and T.shape == (N_RANDOM + 4, 4, 4)
    pos_m, rot_rad = _errors(T.numpy(), pin_T_base_tool(name, arm.joint_names, q.numpy()))
    assert pos_m <= TOL_POS_M, f"{name}: position differs from pinocchio by {pos_m:.3g} m"
    assert rot_rad <= TOL_ROT_RAD, f"{name}: rotation differs from pinocchio by {rot_rad:.3g} rad"
    assert torch.equal(T[:, 3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64).expand(len(q), 4))


@pytest.mark.parametrize("name", ARMS)
def test_joint_names_units_and_limits_match_pinocchios_model(name):
    arm = _arm(name)
    model, _, _ = _pin_model(name)
    assert arm.units == ("rad",) * arm.n_joints  # both shipped arms are all revolute
    for k, j in enumerate(arm.joint_names):
        jid = model.getJointId(j)
        assert jid < model.njoints, f"{j} is no joint of pinocchio's model"
        iq, iv = model.joints[jid].idx_q, model.joints[jid].idx_v
        assert arm.limits.q_min[k].item() == pytest.approx(model.lowerPositionLimit[iq], abs=1e-12)
        assert arm.limits.q_max[k].item() == pytest.approx(model.upperPositionLimit[iq], abs=1e-12)
        assert arm.limits.qd_max[k].item() == pytest.approx(model.velocityLimit[iv], abs=1e-12)
    # The chain's joints are pinocchio's in the same order along the chain (joint ids grow from the root).
    ids = [model.getJointId(j) for j in arm.joint_names]
    assert ids == sorted(ids)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data(), name=st.sampled_from(ARMS))
def test_fk_matches_pinocchio_anywhere_within_the_limits_including_the_ends(data, name):
    arm = _arm(name)
    q = []
    for lo, hi in zip(arm.limits.q_min.tolist(), arm.limits.q_max.tolist()):
        q.append(data.draw(st.one_of(st.sampled_from([lo, hi]), st.floats(lo, hi, allow_nan=False))))
    q = torch.tensor([q], dtype=torch.float64)
    pos_m, rot_rad = _errors(arm.fk(q).numpy(), pin_T_base_tool(name, arm.joint_names, q.numpy()))
    assert pos_m <= TOL_POS_M and rot_rad <= TOL_ROT_RAD


@pytest.mark.parametrize("name", ARMS)
def test_float32_fk_stays_within_float32_precision_of_float64(name):
    arm = _arm(name)
    q = torch.cat([_within_limits(arm, 2000, seed=5), _corners(arm)])
    T64 = arm.fk(q)
    T32 = arm.fk(q.float())
    assert T32.dtype == torch.float32
    pos_m, rot_rad = _errors(T32.double().numpy(), T64.numpy())
    # float32 carries ~7 digits: about 1e-7 per joint, a few joints and ~1 m of arm.
    assert pos_m <= 1e-5 and rot_rad <= 1e-5


# ---------------------------------------------------------------------------------------------
# Gradients, devices, batches


@pytest.mark.parametrize("name", ARMS)
def test_fk_gradients_match_finite_differences(name):
    arm = _arm(name)
    q = torch.cat([_within_limits(arm, 3, seed=11), _corners(arm)[:2]]).requires_grad_(True)
    assert torch.autograd.gradcheck(arm.fk, (q,), eps=1e-6, atol=1e-7)


@pytest.mark.parametrize("name", ARMS)
def test_fk_has_a_finite_gradient_at_zero_and_a_nonzero_jacobian(name):
    arm = _arm(name)
    q = torch.zeros(1, arm.n_joints, dtype=torch.float64, requires_grad=True)
    (J,) = torch.autograd.grad(arm.fk(q)[..., :3, 3].sum(), q)
    assert torch.isfinite(J).all() and J.abs().sum() > 0


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("name", ARMS)
def test_fk_runs_on_the_models_device_and_agrees_with_cpu(name, device):
    arm = shipped_arm(name, device=device)
    assert arm.device == torch.device(device) and arm.limits.q_min.device == torch.device(device)
    q = _within_limits(arm, 64, seed=3)
    for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 1e-5)):
        T = arm.fk(q.to(device=device, dtype=dtype))
        assert T.device.type == torch.device(device).type and T.dtype == dtype
        assert torch.allclose(T.cpu().double(), _arm(name).fk(q), atol=tol)
    assert torch.equal(arm.to("cpu").fk(q), _arm(name).fk(q))


@pytest.mark.parametrize("name", ARMS)
def test_fk_batches_over_any_leading_dimensions(name):
    arm = _arm(name)
    q = _within_limits(arm, 6, seed=2)
    flat = arm.fk(q)
    assert arm.fk(q[0]).shape == (4, 4) and torch.allclose(arm.fk(q[0]), flat[0], atol=1e-15)
    assert torch.allclose(arm.fk(q.reshape(2, 3, -1)), flat.reshape(2, 3, 4, 4), atol=1e-15)
    assert arm.fk(q[:0]).shape == (0, 4, 4)


# ---------------------------------------------------------------------------------------------
# Numerical extremes (documented in ArmModel.fk: NaN propagates into its own pose only)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("name", ARMS)
def test_a_non_finite_joint_value_gives_nan_in_its_own_pose_only(name, bad):
    arm = _arm(name)
    q = _within_limits(arm, 4, seed=8)
    clean = arm.fk(q)
    q[2, 1] = bad
    T = arm.fk(q)
    assert torch.isnan(T[2, :3]).any()
    keep = [0, 1, 3]
    assert torch.equal(T[keep], clean[keep])


@settings(max_examples=100, deadline=None)
@given(
    name=st.sampled_from(ARMS),
    q=st.lists(st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False), min_size=7, max_size=7),
)
def test_huge_finite_joint_values_still_give_rigid_transforms(name, q):
    arm = _arm(name)
    T = arm.fk(torch.tensor(q[: arm.n_joints], dtype=torch.float64))
    R = T[:3, :3]
    assert torch.isfinite(T).all()
    assert torch.allclose(R.T @ R, torch.eye(3, dtype=torch.float64), atol=1e-12)
    assert torch.linalg.det(R).item() == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("name", ARMS)
def test_check_q_accepts_the_limits_and_refuses_nan_inf_and_values_beyond_them(name):
    arm = _arm(name)
    corners = _corners(arm)
    assert arm.check_q(corners) is corners
    for bad, phrase in ((math.nan, "is nan"), (math.inf, "is inf"), (None, "outside its limits")):
        q = corners.clone()
        q[1, 2] = arm.limits.q_max[2] + 1e-9 if bad is None else bad
        with pytest.raises(KinematicsError, match=rf"q\[1\]: joint '{arm.joint_names[2]}' .*{phrase}"):
            arm.check_q(q)
    q = corners.clone()
    q[0, 0] = arm.limits.q_min[0] - 1e-9
    assert arm.check_q(q, tol=1e-6) is q


@pytest.mark.parametrize("name", ARMS)
def test_a_joint_vector_of_the_wrong_length_dtype_device_or_type_is_refused(name):
    arm = _arm(name)
    n = arm.n_joints
    for q, phrase in (
        (torch.zeros(3, n - 1, dtype=torch.float64), f"length {n - 1}.*has {n} joints"),
        (torch.zeros(n + 1, dtype=torch.float64), f"length {n + 1}.*has {n} joints"),
        (torch.tensor(0.0, dtype=torch.float64), "a scalar"),
        (torch.zeros(2, n, dtype=torch.int64), "float64 or float32"),
        (np.zeros((2, n)), "must be a torch tensor"),
        (torch.zeros(2, n, device="meta"), "is on meta"),
    ):
        with pytest.raises(KinematicsError, match=phrase) as err:
            arm.fk(q)
        assert err.value.field == "q" and "\n" not in str(err.value)
    with pytest.raises(KinematicsError, match=", ".join(arm.joint_names)):
        arm.fk(torch.zeros(n - 1, dtype=torch.float64))


def test_an_unusable_device_is_one_clear_error():
    with pytest.raises(KinematicsError, match="device 'no-such-device'"):
        shipped_arm("panda", device="no-such-device")


# ---------------------------------------------------------------------------------------------
# Bad URDFs: one line naming the file and what is wrong

PANDA = ("panda_link0", "panda_hand")


def _panda_text() -> str:
    return shipped_urdf("panda").read_text()


def _variant(tmp_path: Path, old: str, new: str, count: int = 1) -> Path:
    text = _panda_text()
    assert old in text, old
    p = tmp_path / "arm.urdf"
    p.write_text(text.replace(old, new, count))
    return p


J2_LIMIT = 'lower="-1.8326" upper="1.8326" velocity="2.1750"'
J2 = '<joint name="panda_joint2" type="revolute">'


@pytest.mark.parametrize(
    "old, new, phrase",
    [
        (J2_LIMIT, 'lower="nan" upper="1.8326" velocity="2.1750"', "joint 'panda_joint2': <limit lower> is nan"),
        (J2_LIMIT, 'lower="-1.8326" upper="inf" velocity="2.1750"', "joint 'panda_joint2': <limit upper> is inf"),
        (J2_LIMIT, 'lower="-1.8326" upper="1.8326" velocity="-inf"', "joint 'panda_joint2': <limit velocity> is -inf"),
        (J2_LIMIT, 'lower="-1.8326" upper="1.8326" velocity="0"', "<limit velocity> must be > 0"),
        (J2_LIMIT, 'lower="1.9" upper="1.8326" velocity="2.1750"', "<limit lower> 1.9 exceeds upper"),
        (J2_LIMIT, 'upper="1.8326" velocity="2.1750"', "joint 'panda_joint2': its <limit> gives no lower"),
        (J2_LIMIT, 'lower="-1.8326" upper="1.8326"', "its <limit> gives no velocity"),
        (
            J2_LIMIT,
            'lower="-1.8326" upper="one" velocity="2.1750"',
            "joint 'panda_joint2' <limit upper>='one' is not a number",
        ),
        (
            'rpy="-1.57079632679 0 0" xyz="0 0 0"',
            'rpy="-1.57079632679 0" xyz="0 0 0"',
            "<origin rpy>='-1.57079632679 0': expected 3",
        ),
        (
            'rpy="-1.57079632679 0 0" xyz="0 0 0"',
            'rpy="-1.57079632679 0 0" xyz="nan 0 0"',
            "joint 'panda_joint2': its <origin> is not finite",
        ),
        (J2, '<joint name="panda_joint2" type="continuous">', "type 'continuous' in the chain has no position limits"),
        (J2, '<joint name="panda_joint2" type="floating">', "type 'floating' in the chain is not an arm joint"),
        (J2, '<joint name="panda_joint2" type="twisty">', "unknown type 'twisty'"),
        (J2, J2 + '<mimic joint="panda_joint1"/>', "joint 'panda_joint2': a mimic joint in the chain"),
        (J2, J2 + '<axis xyz="0 0 0"/>', "its <axis xyz> must be a finite non-zero vector"),
        (J2, '<joint name="panda_joint1" type="revolute">', "two joints are called 'panda_joint1'"),
        ('<link name="panda_link1">', '<xacro:property name="a" value="1"/><link name="panda_link1">', "a xacro file"),
        (J2_LIMIT, 'lower="${-pi/2}" upper="1.8326" velocity="2.1750"', "a xacro file"),
        ('<robot name="panda"', '<!DOCTYPE robot [<!ENTITY e "x">]>\n<robot name="panda"', "DOCTYPE is refused"),
        ("</robot>", "", "not well-formed XML"),
    ],
)
def test_a_bad_urdf_is_refused_in_one_line_naming_the_file_and_the_field(tmp_path, old, new, phrase):
    p = _variant(tmp_path, old, new)
    with pytest.raises(KinematicsError) as err:
        load_arm(p, *PANDA)
    msg = str(err.value)
    assert msg.startswith(f"{p}: ") and phrase in msg and "\n" not in msg, msg


@pytest.mark.parametrize(
    "links, field, phrase",
    [
        (
            ("panda_link0", "panda_gripper"),
            "tool_link",
            "tool_link 'panda_gripper' is not a link of the URDF (its links: ",
        ),
        (("base", "panda_hand"), "base_link", "base_link 'base' is not a link of the URDF"),
        (("panda_hand", "panda_link0"), "tool_link", "tool_link 'panda_link0' is not below base_link 'panda_hand'"),
        (("panda_leftfinger", "panda_rightfinger"), "tool_link", "is not below"),
        (("panda_link7", "panda_link8"), "tool_link", "no revolute or prismatic joint between"),
        (("panda_link0", "panda_link0"), "tool_link", "both 'panda_link0'"),
    ],
)
def test_links_the_urdf_lacks_or_that_form_no_chain_are_refused_naming_the_field(links, field, phrase):
    with pytest.raises(KinematicsError) as err:
        load_arm(shipped_urdf("panda"), *links)
    assert err.value.field == field and phrase in str(err.value) and str(shipped_urdf("panda")) in str(err.value)


def test_a_missing_directory_fifo_or_oversized_urdf_is_refused_before_parsing(tmp_path):
    cases = {tmp_path / "none.urdf": "no such URDF file", tmp_path: "a directory, expected a URDF file"}
    fifo = tmp_path / "pipe.urdf"
    os.mkfifo(fifo)  # opened without blocking and refused: nothing waits for a writer
    cases[fifo] = "not a regular file"
    big = tmp_path / "big.urdf"
    with open(big, "wb") as f:
        f.truncate(MAX_URDF_BYTES + 1)  # sparse: the size is refused before a byte is read
    cases[big] = f"{MAX_URDF_BYTES + 1} bytes, larger than a URDF may be"
    for path, phrase in cases.items():
        with pytest.raises(KinematicsError, match=phrase) as err:
            load_arm(path, *PANDA)
        assert str(path) in str(err.value) and err.value.field == "urdf"


def test_a_urdf_outside_its_root_is_refused(tmp_path):
    root = tmp_path / "scene"
    root.mkdir()
    outside = tmp_path / "arm.urdf"
    outside.write_text(_panda_text())
    (root / "link.urdf").symlink_to(outside)
    for name in ("../arm.urdf", str(outside), "link.urdf"):
        with pytest.raises(KinematicsError, match="lies outside"):
            load_arm(name, *PANDA, root=root)
    (root / "arm.urdf").write_text(_panda_text())
    assert load_arm("arm.urdf", *PANDA, root=root).n_joints == 7


def test_meshes_are_never_opened_so_any_mesh_reference_loads(tmp_path):
    text = _panda_text().replace("package://meshes/collision/link0.obj", "/no/such/dir/link0.dae", 1)
    text = text.replace("package://meshes/collision/link1.obj", "package://nowhere/link1.stl", 1)
    text = text.replace("package://meshes/collision/link2.obj", "https://example.invalid/link2.obj", 1)
    p = tmp_path / "arm.urdf"
    p.write_text(text)
    q = _within_limits(_arm("panda"), 16, seed=1)
    assert torch.equal(load_arm(p, *PANDA).fk(q), _arm("panda").fk(q))


def test_a_prismatic_joint_moves_the_tool_along_its_axis_in_metres(tmp_path):
    urdf = """<robot name="slide">
      <link name="base"/><link name="carriage"/><link name="tool"/>
      <joint name="rail" type="prismatic"><parent link="base"/><child link="carriage"/>
        <origin xyz="0.1 0 0" rpy="0 0 1.5707963267948966"/><axis xyz="1 0 0"/>
        <limit lower="0" upper="0.5" velocity="0.2" effort="10"/></joint>
      <joint name="flange" type="fixed"><parent link="carriage"/><child link="tool"/><origin xyz="0 0 0.2"/></joint>
    </robot>"""
    p = tmp_path / "slide.urdf"
    p.write_text(urdf)
    arm = load_arm(p, "base", "tool")
    assert arm.joint_names == ("rail",) and arm.units == (JOINT_UNITS["prismatic"],)
    T = arm.fk(torch.tensor([[0.0], [0.25]], dtype=torch.float64))
    # The rail's x axis is the base's y axis (rotated 90 deg about z): 0.25 m along it.
    assert torch.allclose(T[:, :3, 3], torch.tensor([[0.1, 0.0, 0.2], [0.1, 0.25, 0.2]], dtype=torch.float64))
    assert torch.autograd.gradcheck(arm.fk, (torch.tensor([[0.1]], dtype=torch.float64, requires_grad=True),))


# ---------------------------------------------------------------------------------------------
# The shipped arms and their provenance


def test_the_shipped_arm_folders_are_the_registry():
    folder = shipped_urdf("panda").parent.parent
    assert sorted(p.name for p in folder.iterdir() if p.is_dir()) == ARMS


@pytest.mark.parametrize("name", ARMS)
def test_each_shipped_urdf_matches_its_provenance_record_and_carries_its_licence(name):
    prov = read_provenance(name)
    for key in ("package", "version", "path_in_package", "licence", "sha256", "file"):
        assert prov.get(key), f"{name}/{PROVENANCE_JSON} lacks {key}"
    urdf = shipped_urdf(name)
    assert prov["file"] == urdf.name
    assert hashlib.sha256(urdf.read_bytes()).hexdigest() == prov["sha256"]
    assert (urdf.parent / "LICENSE").stat().st_size > 500
    assert sorted(p.name for p in urdf.parent.iterdir()) == sorted([urdf.name, PROVENANCE_JSON, "LICENSE"])
    assert json.loads((urdf.parent / PROVENANCE_JSON).read_text()) == prov


@pytest.mark.parametrize("name", ARMS)
def test_read_chain_is_the_models_chain_and_its_arrays_are_read_only(name):
    chain = read_chain(shipped_urdf(name), *SHIPPED_ARMS[name])
    assert chain.joint_names == _arm(name).joint_names and chain.T_fixed.shape == (len(chain.joint_names) + 1, 4, 4)
    with pytest.raises(ValueError):
        chain.q_min[0] = 0.0


def test_an_unknown_shipped_arm_lists_the_shipped_ones():
    with pytest.raises(KinematicsError, match="no shipped arm 'kuka'; advobj ships: panda, ur5"):
        shipped_urdf("kuka")


# ---------------------------------------------------------------------------------------------
# The scene config (sim.spec.ArmModelConfig)


def _scene_with_arm(tmp_path: Path, arm: dict | None, name: str = "scene.yaml") -> Path:
    data = default_scene().model_dump(mode="json")
    if arm is not None:
        data["arm"] = arm
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data))
    return p


def test_a_scene_without_an_arm_dumps_exactly_as_before():
    spec = default_scene()
    assert spec.arm is None and "arm" not in spec.model_dump()


def test_a_scene_naming_a_shipped_arm_loads_it(tmp_path):
    spec = load_scene(_scene_with_arm(tmp_path, {"urdf": "ur5", "base_link": "base_link", "tool_link": "tool0"}))
    assert spec.arm == ArmModelConfig(urdf="ur5", base_link="base_link", tool_link="tool0")
    assert spec.model_dump()["arm"]["urdf"] == "ur5"
    q = _within_limits(_arm("ur5"), 8, seed=4)
    assert torch.equal(spec.arm.load().fk(q), _arm("ur5").fk(q))
    assert scene_from_dict(spec.model_dump()) == spec


def test_a_scene_names_its_own_urdf_relative_to_the_scene_file(tmp_path):
    (tmp_path / "robots").mkdir()
    (tmp_path / "robots" / "my_panda.urdf").write_text(_panda_text())
    spec = load_scene(
        _scene_with_arm(tmp_path, {"urdf": "robots/my_panda.urdf", "base_link": PANDA[0], "tool_link": PANDA[1]})
    )
    assert Path(spec.arm.urdf) == (tmp_path / "robots" / "my_panda.urdf").resolve()
    assert spec.arm.load().joint_names == _arm("panda").joint_names
    assert urdf_source("panda") == shipped_urdf("panda")


@pytest.mark.parametrize(
    "arm, field, phrase",
    [
        (
            {"urdf": "panda", "base_link": "panda_link0", "tool_link": "hand"},
            "arm.tool_link",
            "tool_link 'hand' is not a link",
        ),
        (
            {"urdf": "panda", "base_link": "link0", "tool_link": "panda_hand"},
            "arm.base_link",
            "base_link 'link0' is not a link",
        ),
        ({"urdf": "../outside.urdf", "base_link": "a", "tool_link": "b"}, "arm.urdf", "lies outside"),
        ({"urdf": "missing.urdf", "base_link": "a", "tool_link": "b"}, "arm.urdf", "no such URDF file"),
        ({"urdf": "broken.urdf", "base_link": "a", "tool_link": "b"}, "arm.urdf", "not well-formed XML"),
        ({"urdf": "panda", "base_link": "panda_link0"}, "arm.tool_link", "Field required"),
        (
            {"urdf": "panda", "base_link": "panda_link0", "tool_link": "panda_hand", "mesh": "x"},
            "arm.mesh",
            "Extra inputs",
        ),
    ],
)
def test_a_scene_with_a_bad_arm_is_one_line_naming_the_scene_file_and_the_field(tmp_path, arm, field, phrase):
    (tmp_path / "broken.urdf").write_text("<robot name='x'><link name='a'>")
    (tmp_path.parent / "outside.urdf").write_text(_panda_text())
    p = _scene_with_arm(tmp_path, arm)
    with pytest.raises(SpecError) as err:
        load_scene(p)
    msg = str(err.value)
    assert msg.startswith(f"{p}: ") and f"{field}: " in msg and phrase in msg and "\n" not in msg, msg
