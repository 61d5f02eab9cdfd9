"""The objective as terms: PCGrad over N gradients, a new term without touching the loop, generic history.

The textures pinned below were produced by the attack loop before the objective had terms (commit
3e31af9, the two-gradient ``pair_gradients``/``pcgrad`` path): the term objective reproduces them
bit for bit, so every committed result stays reproducible.
"""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from attack.objective import NEEDS, Objective, PoseTerm, SaliencyTerm, build_objective
from attack.optimize import AttackRun, attack_step, resolve_config, run_attack
from attack.pcgrad import pcgrad, pcgrad_many, sum_gradients
from attack.state import AttackState, History
from sim.configs import sample_pool
from sim.policies.policy import VisuomotorPolicy
from sim.spec import default_scene

TINY = {
    "iterations": 3,
    "num_envs": 2,
    "rollout_steps": 2,
    "texture_size": 16,
    "pool_size": 8,
    "lr": 0.5,
    "validation_every": 0,
    "lambda_sal": 1.0,
}
# sha256 (first 16 hex) of the final texture's float32 bytes under the pre-terms loop (commit 3e31af9),
# whose frames were shaded from the measured albedo passes: HybridRenderer(shading="passes")
# reproduces them bit for bit (the committed results were made that way). The bytes depend on the
# CPU's float kernels: the same AVX-512 build of torch gives other bits on an AMD EPYC than on an
# Intel Xeon, so each vendor has the digests its own run of the reference commit gave (on the AMD
# one, 3e31af9's code and this loop both gave the digests below; a CPU of another vendor skips).
PINNED_BY_VENDOR = {
    "GenuineIntel": {
        "default": "56b4d13d766672ac",
        "untargeted": "954e70d28dc1aa1b",
        "nopose": "0eecbe40a5ed71c2",
        "nopcgrad": "edf6fdfd0cd6fbba",
        "print": "1f4dea7b36b5cf54",
    },
    "AuthenticAMD": {
        "default": "614ebd83bd35eb67",
        "untargeted": "20b53587b72f648b",
        "nopose": "ba83cafdcdd060a0",
        "nopcgrad": "1e369bed5de1629a",
        "print": "10f1866f171e7eb6",
    },
}
OVERRIDES = {
    "default": {},
    "untargeted": {"loss": "untargeted"},
    "nopose": {"use_pose": False},
    "nopcgrad": {"pcgrad": False},
    "print": {"print_aware": True, "light_randomization": True},
}
# The same runs with the default deferred shading (issue 26 part 5: pyrender's BRDF in torch, no
# albedo passes; pinned from commit 700a68e, which introduced it). The shading values differ from
# the 8-bit measurement by its quantisation (|D| <= 0.02, |S| <= 0.002 linear), so the textures
# differ; the deferred shading is within 1/255 of pyrender per pixel over the consistency grid
# (tests/attack/test_render_shading.py), the measured one within 1.2/255, and the composite stays
# within 2/255 (tests/attack/test_render.py).
PINNED_DEFERRED_BY_VENDOR = {
    "GenuineIntel": {
        "default": "1acef1ff1842e7f7",
        "untargeted": "06a6266a9b40ff80",
        "nopose": "1eb1e4cbfca7d8bc",
        "nopcgrad": "2c390434dc5496c7",
        "print": "f770909283cab0a7",
    },
    "AuthenticAMD": {
        "default": "e747aa29aa93e00c",
        "untargeted": "33fa85e471c377b2",
        "nopose": "6e8c37fbc957e491",
        "nopcgrad": "8e34924f6f4ce70d",
        "print": "57a6efef97216f79",
    },
}


def _cpu_vendor() -> str:
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("vendor_id"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown"


def _old_pcgrad(g1, g2, eps=1e-20):
    """The two-gradient PCGrad as it was written before N terms (the reference)."""
    a, b = g1.reshape(-1), g2.reshape(-1)
    dot = torch.dot(a, b)
    if dot >= 0:
        return g1 + g2
    na, nb = torch.dot(a, a), torch.dot(b, b)
    p1 = g1 - (dot / nb.clamp_min(eps)) * g2 if nb > eps else g1
    p2 = g2 - (dot / na.clamp_min(eps)) * g1 if na > eps else g2
    return p1 + p2


@pytest.fixture(scope="module")
def spec_pool():
    spec = default_scene()
    return spec, sample_pool(spec, 8, seed=5, part="attack")


def _run(spec, pool, **over):
    torch.manual_seed(0)
    return AttackRun(
        VisuomotorPolicy(arch="small_cnn", image_size=32), spec, resolve_config("quick", {**TINY, **over}), pool=pool
    )


@pytest.mark.parametrize("shading", ["passes", "deferred"])
@pytest.mark.parametrize("name", sorted(OVERRIDES))
def test_the_term_objective_reproduces_the_two_gradient_loop_bit_for_bit(spec_pool, name, shading):
    vendor = _cpu_vendor()
    pinned = (PINNED_BY_VENDOR if shading == "passes" else PINNED_DEFERRED_BY_VENDOR).get(vendor)
    if pinned is None:
        pytest.skip(f"no digests pinned for CPU vendor {vendor!r} (float kernels differ by vendor)")
    digest = pinned[name]
    run = _run(*spec_pool, **OVERRIDES[name])
    run.hybrid.shading = shading  # the frame source shares this renderer
    try:
        run_attack(run, progress=False)
        got = hashlib.sha256(run.state.texture.numpy().tobytes()).hexdigest()[:16]
    finally:
        run.close()
    assert got == digest


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.floats(-1e6, 1e6, allow_nan=False, width=32), min_size=8, max_size=8),
    st.lists(st.floats(-1e6, 1e6, allow_nan=False, width=32), min_size=8, max_size=8),
)
def test_pcgrad_of_two_gradients_equals_the_two_gradient_formula_exactly(a, b):
    g1, g2 = torch.tensor(a).reshape(2, 4), torch.tensor(b).reshape(2, 4)
    assert torch.equal(pcgrad_many([g1, g2]), _old_pcgrad(g1, g2))
    assert torch.equal(pcgrad(g1, g2), _old_pcgrad(g1, g2))


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-1e3, 1e3, allow_nan=False, width=32), min_size=12, max_size=12))
def test_pcgrad_over_three_gradients_is_finite_and_resolves_each_first_conflict(v):
    g = [torch.tensor(v[4 * i : 4 * i + 4]) for i in range(3)]
    out = pcgrad_many(g)
    assert torch.isfinite(out).all()
    # with no conflict at all it is the plain sum
    if all(float(torch.dot(g[i], g[j])) >= 0 for i in range(3) for j in range(i + 1, 3)):
        assert torch.equal(out, sum_gradients(g))


def test_pcgrad_passes_one_gradient_and_zero_gradients_through():
    g = torch.tensor([1.0, -2.0, 3.0])
    z = torch.zeros(3)
    assert torch.equal(pcgrad_many([g]), g)
    assert torch.equal(pcgrad_many([g, z, z]), g)
    assert torch.equal(pcgrad_many([z, z]), z)
    with pytest.raises(ValueError):
        pcgrad_many([])


def test_three_pairwise_conflicting_gradients_are_projected_off_each_other():
    g = [torch.tensor([1.0, 0.0]), torch.tensor([-0.5, 1.0]), torch.tensor([-0.5, -1.0])]
    out = pcgrad_many(g)
    assert torch.isfinite(out).all() and not torch.equal(out, sum_gradients(g))


def test_build_objective_names_the_papers_terms_for_each_config():
    ep = default_scene().episode
    cfg = resolve_config("quick")
    assert [t.name for t in build_objective(cfg, ep).terms] == ["pose", "saliency"]
    assert [t.name for t in build_objective(cfg.model_copy(update={"use_saliency": False}), ep).terms] == ["pose"]
    assert [t.name for t in build_objective(cfg.model_copy(update={"loss": "untargeted"}), ep).terms] == [
        "deviation",
        "saliency",
    ]
    with pytest.raises(ValueError, match="unique"):
        Objective([SaliencyTerm(1.0), SaliencyTerm(2.0)])


class _Brightness:
    """A term written outside the attack package: darken the object's pixels (reads the images)."""

    name = "brightness"
    weight = 0.5
    needs = frozenset({"masks"})
    parts = ("mean",)

    @staticmethod
    def schedule(iteration: int, iterations: int) -> float:
        return 1.0 if iteration < 2 else 0.0  # on for the first two iterations only

    def loss(self, batch, weight):
        adv, _ = batch.masks
        m = adv[:, None].to(batch.images.dtype)
        per = (batch.images * m).sum(dim=(1, 2, 3)) / m.sum(dim=(1, 2, 3)).clamp_min(1.0)
        return weight * per.sum(), {"mean": per.detach()}


def test_a_new_term_joins_the_loop_and_the_checkpoint_without_touching_either(spec_pool, tmp_path):
    spec, pool = spec_pool
    run = _run(spec, pool)
    try:
        ep = spec.episode
        run.objective = Objective([PoseTerm(ep.max_step_m, ep.max_step_rad, 0.1), _Brightness()])
        before = run.state.texture.clone()
        infos = [attack_step(run, run.state) for _ in range(3)]
        h = run.state.history
        assert set(h.terms) == {"pose", "pose.ori", "pose.dist", "brightness", "brightness.mean"}
        assert all(len(v) == 3 for v in h.terms.values())
        assert h.terms["brightness"][2] == 0.0 and h.terms["brightness"][0] != 0.0  # its schedule turned it off
        assert all(set(i["terms"]) == {"pose", "brightness"} for i in infos)
        assert not torch.equal(before, run.state.texture)
        # the checkpoint format is unchanged: the state round-trips with the new term's history
        run.state.write(tmp_path, run.cfg.model_dump())
        back, _ = AttackState.read(tmp_path, "cpu")
        assert back.history.terms == h.terms and torch.equal(back.texture, run.state.texture)
    finally:
        run.close()


def test_a_term_that_asks_for_an_input_nobody_offers_is_refused():
    class _Bad:
        name, weight, needs, parts = "bad", 1.0, frozenset({"depth"}), ()

    with pytest.raises(ValueError, match="depth"):
        Objective([_Bad()])
    assert "actions" in NEEDS and "clean_actions" in NEEDS


def test_a_history_written_before_terms_had_names_reads_into_terms():
    old = {
        "iteration": [0, 1],
        "loss_pose": [0.5, 0.4],
        "loss_saliency": [0.0, 0.0],
        "loss_ori": [0.3, 0.2],
        "loss_dist": [2.0, 2.0],
        "grad_norm": [1.0, 1.0],
        "stage": [0, 0],
        "skipped": 0,
        "seconds": 1.0,
        "val_iteration": [],
        "val_t_asr": [],
        "val_dist_m": [],
        "val_seconds": [],
        "val_probe_pose": [],
    }
    h = History.from_dict(json.loads(json.dumps(old)))
    assert h.terms == {"pose": [0.5, 0.4], "pose.ori": [0.3, 0.2], "pose.dist": [2.0, 2.0]}
    assert h.loss_pose == [0.5, 0.4] and h.loss_saliency == [0.0, 0.0]  # a term that was off reads as 0
    assert History.from_dict(h.to_dict()) == h


def test_the_loss_terms_stay_finite_at_extreme_textures(spec_pool):
    run = _run(*spec_pool)
    try:
        for fill in (0.0, 1.0):
            run.state.texture = torch.full_like(run.state.texture, fill)
            info = attack_step(run, run.state)
            assert all(np.isfinite(v) for v in info["terms"].values())
            assert torch.isfinite(run.state.texture).all()
    finally:
        run.close()
