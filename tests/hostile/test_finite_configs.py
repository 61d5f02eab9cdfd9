"""Every float of every config model is finite: the shared strict base refuses NaN and inf.

The structural test walks every pydantic model defined in the project's packages, so a new
model that forgets the base fails here; the concrete tests feed NaN/inf through the real loaders.
"""

from __future__ import annotations

import importlib
import math
import pkgutil

import pytest
from pydantic import BaseModel

from sim.configio import StrictModel

PACKAGES = ("sim", "calibration", "robot_io", "attack", "trials")
PENDING: set[str] = set()  # models allowed to stay off the strict base for now (none)
SKIP_MODULES = ("sim.gl_fastpath",)


def _project_models() -> dict[str, type[BaseModel]]:
    found: dict[str, type[BaseModel]] = {}
    for pkg_name in PACKAGES:
        pkg = importlib.import_module(pkg_name)
        for info in pkgutil.walk_packages(pkg.__path__, pkg_name + "."):
            if info.name.startswith(SKIP_MODULES):
                continue
            try:
                mod = importlib.import_module(info.name)
            except ImportError:  # an optional vendor SDK
                continue
            for obj in vars(mod).values():
                if isinstance(obj, type) and issubclass(obj, BaseModel) and obj.__module__ == info.name:
                    found[f"{obj.__module__}.{obj.__qualname__}"] = obj
    return found


def test_every_project_model_refuses_nan_and_inf_and_unknown_keys():
    models = _project_models()
    assert len(models) > 30, sorted(models)
    loose = sorted(
        name
        for name, m in models.items()
        if name not in PENDING
        and (m.model_config.get("allow_inf_nan", True) or m.model_config.get("extra") != "forbid")
    )
    assert loose == [], f"models that accept NaN/inf or unknown keys (derive from sim.configio.StrictModel): {loose}"
    assert all(issubclass(m, StrictModel) for n, m in models.items() if n not in PENDING)


@pytest.mark.parametrize("bad", [".nan", ".inf", "-.inf"])
def test_hardware_T_tcp_cam_with_nan_or_inf_is_refused_naming_the_field(tmp_path, bad):
    from robot_io.config import load_T_tcp_cam
    from sim.errors import AdvobjError

    p = tmp_path / "T_tcp_cam.yaml"
    p.write_text(f"T_tcp_cam:\n  translation_m: [0, 0, {bad}]\n  rotvec_rad: [0, 0, 0]\n")
    with pytest.raises(AdvobjError) as info:
        load_T_tcp_cam(p)
    msg = str(info.value)
    assert str(p) in msg and "translation_m" in msg and "\n" not in msg


@pytest.mark.parametrize(
    "field,bad", [("workspace_max_m", "[1, 1, .nan]"), ("max_step_m", ".inf"), ("max_trial_s", ".nan")]
)
def test_hardware_safety_limits_with_nan_or_inf_are_refused(tmp_path, field, bad):
    from robot_io.config import load_hardware_config
    from robot_io.errors import HardwareConfigError

    safety = {"workspace_min_m": "[0, 0, 0]", "workspace_max_m": "[1, 1, 1]", field: bad}
    p = tmp_path / "hw.yaml"
    p.write_text(
        "camera: {type: sim}\narm: {type: sim}\nsafety:\n" + "".join(f"  {k}: {v}\n" for k, v in safety.items())
    )
    with pytest.raises(HardwareConfigError, match=rf"safety\.{field}"):
        load_hardware_config(p)


def test_scene_and_calibration_floats_are_finite():
    from calibration.io import PoseModel
    from sim.spec import SpecError, default_scene, scene_from_dict

    doc = default_scene().model_dump(mode="json")
    doc["camera"]["fov_deg"] = math.inf
    with pytest.raises(SpecError, match=r"camera\.fov_deg"):
        scene_from_dict(doc)
    with pytest.raises(ValueError):
        PoseModel(translation_m=(0.0, math.nan, 0.0))
