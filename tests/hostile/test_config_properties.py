"""Property tests: merged config values are validated again, floats stay finite, bounds hold.

``sim.configio.merged`` is how a value from one input (a plan's ``control_hz``, a policy's image
size, a path resolved against its YAML) lands in another config. Whatever hypothesis throws at
it, the result is either refused with an ``AdvobjError`` naming the field, or a model whose every
value passes validation again.
"""

from __future__ import annotations

import math

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from robot_io.safety import SafetyLimits
from sim.configio import ConfigError, merged
from sim.errors import AdvobjError

SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True) | st.sampled_from(
    [0.0, -0.0, 1e-300, 1e-6, 1e20, 1e308, -1.0]
)
ANY_INT = st.integers(min_value=-(10**21), max_value=10**21)

LIMITS = SafetyLimits(workspace_min_m=(-0.5, -0.5, 0.0), workspace_max_m=(0.5, 0.5, 0.8))


def _floats_in(obj):
    """Every float in a dumped model (nested dicts, lists, tuples)."""
    if isinstance(obj, float):
        yield obj
    elif isinstance(obj, dict):
        for v in obj.values():
            yield from _floats_in(v)
    elif isinstance(obj, (list, tuple)):
        for v in obj:
            yield from _floats_in(v)


def _holds(model) -> None:
    """The model re-validates to itself and holds only finite floats."""
    again = type(model).model_validate(model.model_dump())
    assert again == model
    assert all(math.isfinite(x) for x in _floats_in(model.model_dump()))


def _models():
    from sim.policies.dagger import DaggerConfig
    from sim.policies.ppo import PPOConfig
    from sim.policies.rollout import EnvConfig
    from sim.spec import default_scene
    from trials.real.plan import TrialPlan, make_plan

    spec = default_scene()
    plan = make_plan(spec, 0, ["A"], ["cube"], ["clean"], {}, n_tcp_poses=1, n_object_layouts=1)
    assert isinstance(plan, TrialPlan)
    return {
        "safety": LIMITS,
        "env": EnvConfig(),
        "dagger": DaggerConfig(),
        "ppo": PPOConfig(),
        "plan": plan,
        "episode": spec.episode,
        "camera": spec.camera,
        "init": spec.init,
    }


MODELS = _models()
FIELDS = [
    (name, f)
    for name, m in MODELS.items()
    for f, info in type(m).model_fields.items()
    if info.annotation in (float, int) or "float" in str(info.annotation) or "int" in str(info.annotation)
]


@pytest.mark.parametrize("name,field", FIELDS, ids=[f"{n}.{f}" for n, f in FIELDS])
@SETTINGS
@given(value=ANY_FLOAT | ANY_INT)
def test_a_merged_number_is_refused_or_holds(name, field, value):
    model = MODELS[name]
    try:
        out = merged(model, {field: value}, what=name)
    except ConfigError as err:  # refused in one line naming the field
        assert field in str(err) and "\n" not in str(err)
        return
    assert not (isinstance(value, float) and not math.isfinite(value)), f"{name}.{field} accepted {value}"
    _holds(out)


@SETTINGS
@given(hz=ANY_FLOAT)
def test_the_plans_control_rate_reaches_the_safety_layer_validated(hz):
    """The session's merge: period 1/control_hz is accepted only inside the safety layer's bounds."""
    from robot_io.config import hardware_config_from_dict
    from trials.real.session import _safety_at_plan_rate

    hw = hardware_config_from_dict(
        {"camera": {"type": "sim"}, "arm": {"type": "sim"}, "safety": LIMITS.model_dump(mode="json")}
    )
    plan = MODELS["plan"].model_copy(update={"control_hz": hz})  # a plan that skipped validation
    try:
        out = _safety_at_plan_rate(hw, plan, MODELS["episode"], log=lambda *_: None)
    except AdvobjError:
        return
    except ZeroDivisionError:
        assert hz == 0
        return
    assert 0.001 <= out.safety.control_period_s <= 2.0
    assert math.isclose(out.safety.control_period_s, 1.0 / hz, rel_tol=1e-9) or math.isclose(
        LIMITS.control_period_s, 1.0 / hz, rel_tol=1e-6
    )
    _holds(out)


@pytest.mark.parametrize(
    "field,value",
    [
        ("control_hz", math.inf),
        ("control_hz", 1e-6),
        ("control_hz", 0.0),
        ("control_hz", 1e6),
        ("max_steps", 10**20),
        ("max_steps", 0),
        ("radius_m", math.nan),
        ("placement_tolerance_rad", 10.0),
    ],
)
def test_plan_values_out_of_bounds_are_refused_at_load(tmp_path, field, value):
    import yaml

    from trials.real.plan import PlanError, load_plan

    data = MODELS["plan"].model_dump(mode="json")
    data[field] = value
    p = tmp_path / "plan.yaml"
    p.write_text(yaml.safe_dump(data))
    with pytest.raises(PlanError) as info:
        load_plan(p)
    assert field in str(info.value) and str(p) in str(info.value)


def test_hardware_paths_resolved_by_a_validated_merge(tmp_path):
    from robot_io.config import load_hardware_config

    p = tmp_path / "hw.yaml"
    p.write_text(
        "camera: {type: replay, path: frames}\narm: {type: sim}\nsafety: {workspace_min_m: [0, 0, 0], workspace_max_m: "
        "[1, 1, 1]}\n"
        "T_tcp_cam: hand_eye.yaml\n"
    )
    cfg = load_hardware_config(p)
    assert cfg.camera.path == tmp_path / "frames" and cfg.T_tcp_cam == tmp_path / "hand_eye.yaml"
    _holds(cfg)
