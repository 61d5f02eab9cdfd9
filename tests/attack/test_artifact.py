"""The texture folder's one owner: round trip, provenance, and refusal of anything malformed."""

import json

import numpy as np
import pytest
import torch

from attack.artifact import (
    CONFIG_RECORD,
    TEXTURE_NPY,
    ArtifactError,
    AttackArtifact,
    overlap_count,
    read_config_record,
    write_config_record,
)


def _art(seed=0, size=8):
    tex = np.random.default_rng(seed).random((size, size, 3)).astype(np.float32)
    return AttackArtifact(tex, {"attack": {"adversarial_mesh": "cube", "iterations": 3}}, seed=7)


def test_a_saved_folder_loads_back_bit_identical_with_its_mesh_seed_and_texture_hash(tmp_path):
    _art().save(tmp_path / "a")
    b = AttackArtifact.load(tmp_path / "a")
    assert np.array_equal(b.texture, _art().texture) and b.mesh == "cube" and b.seed == 7
    assert b.sha256 == AttackArtifact.texture_sha256(tmp_path / "a") and len(b.sha256) == 64
    assert (tmp_path / "a" / "texture.png").is_file() and b.trained_on is None
    assert b.texture_u8.dtype == np.uint8 and b.texture_u8.shape == (8, 8, 3)


def test_from_tensor_clamps_and_keeps_the_channel_layout(tmp_path):
    t = torch.zeros(3, 4, 4)
    t[0] = 2.0  # out of range: clamped to 1
    t[2, 1, 2] = 0.5
    a = AttackArtifact.from_tensor(t, {"attack": {}})
    assert a.texture.shape == (4, 4, 3) and a.texture[..., 0].max() == 1.0 and a.texture[1, 2, 2] == 0.5


def test_provenance_run_json_records_the_commit_and_best_folders_use_the_run_record(tmp_path):
    from sim.configs import sample_pool
    from sim.spec import default_scene

    _art().save(tmp_path, run="provenance")
    doc = json.loads((tmp_path / "run.json").read_text())
    assert doc["config"]["attack"]["adversarial_mesh"] == "cube" and "git_commit" in doc
    spec = default_scene()
    attack, validation = sample_pool(spec, 2, part="attack"), sample_pool(spec, 1, part="validation")
    write_config_record(tmp_path, attack, validation)
    _art(1).save(tmp_path / "best")
    seen = AttackArtifact.load(tmp_path / "best").trained_on
    assert overlap_count(attack + validation, seen) == 3
    assert overlap_count(sample_pool(spec, 5, part="evaluation"), seen) == 0


def test_the_overlap_is_found_by_pose_even_under_another_seed(tmp_path):
    """The check can fail: the same poses drawn under a different seed (another id) still count."""
    import dataclasses

    from sim.configs import config_id, sample_pool
    from sim.spec import default_scene

    spec = default_scene()
    attack = sample_pool(spec, 3, part="attack")
    write_config_record(tmp_path, attack, [])
    seen = read_config_record(tmp_path)
    twin = dataclasses.replace(attack[1], seed=10**6 + 7)  # same poses, another seed: another content id
    assert config_id(twin) != config_id(attack[1])
    assert overlap_count([twin], seen) == 1
    moved = dataclasses.replace(attack[1], r_m=attack[1].r_m + 1e-6)
    assert overlap_count([moved], seen) == 0
    # a record written before pose ids existed still matches by content id
    doc = json.loads((tmp_path / CONFIG_RECORD).read_text())
    for e in doc["attack"]:
        e.pop("pose")
    (tmp_path / CONFIG_RECORD).write_text(json.dumps(doc))
    old = read_config_record(tmp_path)
    assert overlap_count(attack, old) == 3 and overlap_count([twin], old) == 0


@pytest.mark.parametrize(
    ("damage", "match"),
    [
        (lambda d: (d / TEXTURE_NPY).unlink(), "texture.npy: missing"),
        (lambda d: (d / "run.json").unlink(), "run.json: missing"),
        (lambda d: (d / "run.json").write_text("{"), "cannot read config.attack"),
        (lambda d: (d / "run.json").write_text('{"config": {"attack": 3}}'), "cannot read config.attack"),
        (lambda d: np.save(d / TEXTURE_NPY, np.full((4, 4, 3), np.nan, np.float32)), "finite and in \\[0, 1\\]"),
        (lambda d: np.save(d / TEXTURE_NPY, np.zeros((4, 4), np.float32)), "expected an \\(H, W, 3\\) float array"),
        (
            lambda d: np.save(d / TEXTURE_NPY, np.array([{"a": 1}], dtype=object), allow_pickle=True),
            "not a texture array",
        ),
        (lambda d: (d / CONFIG_RECORD).write_text('{"format": "other"}'), "not a configuration record"),
    ],
)
def test_a_damaged_folder_is_one_clear_error_and_a_pickle_is_never_loaded(tmp_path, damage, match):
    _art().save(tmp_path)
    damage(tmp_path)
    with pytest.raises(ArtifactError, match=match):
        AttackArtifact.load(tmp_path)


def test_a_caller_chooses_the_error_type_and_a_file_is_no_folder(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(KeyError):
        AttackArtifact.load(tmp_path / "f", error=KeyError)
