"""SimWorld staging: objects placed from outside, and a scene swapped in place."""

import numpy as np
import pytest

from sim.spec import default_scene
from sim.world import SimWorld


@pytest.fixture(scope="module")
def world():
    w = SimWorld(default_scene(), image_size=(32, 32), seed=0)
    yield w
    w.close()


def test_place_objects_moves_centres_and_keeps_tcp(world):
    T_tcp = world.T_world_tcp
    xyy = np.array([[0.1, -0.05, 0.3], [-0.12, 0.08, -1.0]])[: len(world.spec.objects)]
    world.place_objects(xyy)
    np.testing.assert_allclose(world.T_world_objects[:, :2, 3], xyy[:, :2])
    np.testing.assert_allclose(world.object_center_array[:, :2], xyy[:, :2], atol=0.05)
    np.testing.assert_array_equal(world.T_world_tcp, T_tcp)
    with pytest.raises(ValueError, match="object_xy_yaw"):
        world.place_objects(np.zeros((len(world.spec.objects) + 1, 3)))


def test_set_scene_swaps_mesh_with_a_cached_renderer(world):
    from sim.render import SceneRenderer

    spec = world.spec
    adv = spec.object_index("adversarial")
    objs = [
        o.model_copy(update={"mesh": "cube", "texture": None}) if o.role == "adversarial" else o for o in spec.objects
    ]
    cube = spec.with_updates(objects=[o.model_dump() for o in objs])
    T_objs, T_tcp = world.T_world_objects.copy(), world.T_world_tcp
    before = world.render(with_ids=True).object_mask(adv).sum()
    cached = SceneRenderer(cube, world.width, world.height)
    try:
        world.set_scene(cube, renderer=cached)
        assert world.spec.adversarial.mesh == "cube" and world.renderer is cached
        np.testing.assert_array_equal(world.T_world_objects, T_objs)
        np.testing.assert_array_equal(world.T_world_tcp, T_tcp)
        world.render(with_ids=True)  # renders with the swapped scene
        # Switching back builds an owned renderer; the cached one stays usable for its owner.
        world.set_scene(spec)
        assert world.renderer is not cached
        assert world.render(with_ids=True).object_mask(adv).sum() == before
        cached.render(world.camera_pose(), with_ids=False)
    finally:
        cached.close()
    with pytest.raises(ValueError, match="objects"):
        world.set_scene(
            spec.with_updates(
                objects=[o.model_dump() for o in spec.objects[:2]]
                + [{"name": "extra", "mesh": "cube", "role": "distractor"}]
            )
        )
