"""docs/configuration.md is generated from the pydantic models and must not go stale."""

from pathlib import Path

from tools import docgen

ROOT = Path(__file__).resolve().parents[2]


def test_configuration_md_is_current():
    committed = (ROOT / docgen.DEFAULT_PATH).read_text()
    assert committed == docgen.render(), (
        f"{docgen.DEFAULT_PATH} is stale (a config model changed); regenerate it with: {docgen.REGENERATE}"
    )


def test_every_field_of_every_model_is_documented():
    from attack.optimize import AttackConfig
    from robot_io.config import HardwareConfig, OpenCVCameraConfig, URArmConfig
    from robot_io.safety import SafetyLimits
    from sim.spec import CameraSpec, SceneSpec
    from trials.eval.evaluate import EvalConfig

    text = docgen.render()
    for model in (
        SceneSpec,
        CameraSpec,
        AttackConfig,
        EvalConfig,
        HardwareConfig,
        OpenCVCameraConfig,
        URArmConfig,
        SafetyLimits,
    ):
        section = text.split(f"### {model.__name__}\n", 1)[1].split("\n### ", 1)[0]
        for name in model.model_fields:
            assert f"| `{name}` |" in section, f"{model.__name__}.{name} missing from the reference"


def test_rows_carry_type_default_constraint_and_description():
    from typing import Annotated, Literal

    from pydantic import BaseModel, Field

    class Demo(BaseModel):
        """A demo model."""

        a: int = Field(3, ge=1, le=9, description="an int")
        # the comment above b
        b: Literal["x", "y"] = "x"
        c: Annotated[float, Field(gt=0)] | None = None  # trailing comment
        d: tuple[float, float]

    rows = {r[0]: r[1:] for r in docgen.model_rows(Demo)}
    assert rows["`a`"] == ("int", "`3`", ">= 1, <= 9", "an int")
    assert rows["`b`"] == ('"x" | "y"', '`"x"`', "", "the comment above b")
    assert rows["`c`"] == ("float (> 0) | null", "`null`", "", "trailing comment")
    assert rows["`d`"][:2] == ("tuple[float, float]", "**required**")
    assert "| `a` | int | `3` | >= 1, <= 9 | an int |" in docgen.render_model(Demo)


def test_check_mode_reports_stale_file_and_the_command(tmp_path, capsys):
    stale = tmp_path / "configuration.md"
    stale.write_text("old\n")
    assert docgen.main(["--check", str(stale)]) == 1
    assert docgen.REGENERATE in capsys.readouterr().err
    assert docgen.main(["--write", str(stale)]) == 0
    assert docgen.main(["--check", str(stale)]) == 0


def test_field_notes_name_existing_fields():
    import importlib

    models = {"AttackConfig": "attack.optimize", "SafetyLimits": "robot_io.safety"}
    for model_name, notes in docgen.FIELD_NOTES.items():
        model = getattr(importlib.import_module(models[model_name]), model_name)
        assert set(notes) <= set(model.model_fields), (
            f"{model_name}: notes for unknown fields {set(notes) - set(model.model_fields)}"
        )
