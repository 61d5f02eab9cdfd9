"""Shared fixtures: one sim world (one GL context) for every robot_io test that needs it."""

from __future__ import annotations

import pytest

from robot_io.safety import SafetyLimits


@pytest.fixture(scope="session")
def sim_world():
    from sim.spec import default_scene
    from sim.world import SimWorld

    world = SimWorld(default_scene(), image_size=(48, 64), seed=0)
    yield world
    world.close()


@pytest.fixture
def fresh_world(sim_world):
    """The shared world reset to a known configuration (tests move its gripper)."""
    sim_world.reset(seed=3)
    return sim_world


@pytest.fixture
def limits():
    return SafetyLimits(
        workspace_min_m=(-1.0, -1.0, 0.0),
        workspace_max_m=(1.0, 1.0, 1.0),
        max_step_m=0.02,
        max_step_rad=0.1,
        max_speed_mps=0.5,
        max_speed_radps=2.0,
        max_accel_mps2=1000.0,
        control_period_s=0.05,
        max_frame_age_ms=100.0,
        max_trial_s=60.0,
        positioning_speed_mps=0.2,
    )
