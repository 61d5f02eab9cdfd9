"""The evaluation renders at the policy's input size (never a larger frame to be downsampled)."""

import sim.render
from sim.configs import sample_pool
from sim.policies.checkpoint import load_policy
from sim.spec import default_scene
from trials.eval.conditions import Condition
from trials.eval.evaluate import rollout_condition


def test_eval_rollout_renders_at_the_policy_size(tiny_policy_dir, monkeypatch):
    policy = load_policy(tiny_policy_dir)
    spec = default_scene().with_updates(episode={**default_scene().episode.model_dump(), "max_steps": 2})
    sizes = []
    real = sim.render.SceneRenderer.render

    def spy(self, *a, **k):
        out = real(self, *a, **k)
        sizes.append(out.rgb.shape[:2])
        return out

    monkeypatch.setattr(sim.render.SceneRenderer, "render", spy)
    rollout_condition(policy, spec, Condition("clean"), sample_pool(spec, 2, seed=0), 2, lambda j, r: None)
    S = int(policy.image_size)
    assert sizes and set(sizes) == {(S, S)} and S < spec.camera.width
