"""On real hardware only (``-m hardware``): ``advobj hw check`` against the config named by ADVOBJ_HW_CONFIG.

Never runs in CI (the default ``-m 'not slow and not hardware'`` deselects it). It moves nothing.
"""

from __future__ import annotations

import os

import pytest
from typer.testing import CliRunner

from trials.cli.main import app


@pytest.mark.hardware
def test_hw_check_on_the_lab_config_reports_a_healthy_camera_and_arm():
    path = os.environ.get("ADVOBJ_HW_CONFIG")
    if not path:
        pytest.skip("set ADVOBJ_HW_CONFIG to the cell's hardware YAML")
    result = CliRunner().invoke(app, ["hw", "check", "--config", path, "--frames", "90"])
    assert result.exit_code == 0, result.output
    assert "fault: none" in result.output and "nothing moved" in result.output
