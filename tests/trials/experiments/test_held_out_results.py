"""The committed held-out claim, checked from the committed pools and attack records by content:
no evaluation configuration has the poses of any configuration an attack trained or selected on."""

import json
from pathlib import Path

import pytest

from attack.artifact import overlap_count, read_config_record
from sim.configs import config_id, load_pool, pose_id, sample_config
from sim.spec import default_scene, load_spec

ROOT = Path(__file__).resolve().parents[3]
RESULTS = ROOT / "results"
# Every scene a committed recipe can run in: the built-in one and every shipped scene (the pools name
# theirs by fingerprint; a pool of a scene not among them fails below).
SCENES = [default_scene(), *(load_spec(str(p)) for p in sorted((ROOT / "scenes").glob("*.yaml")))]


def _recipes():
    return sorted(p.name for p in RESULTS.iterdir() if (p / "pools").is_dir() and (p / "attack_configs").is_dir())


def _spec_of(pool_file: Path):
    fp = json.loads(pool_file.read_text())["spec_fingerprint"]
    for spec in SCENES:
        try:
            load_pool(pool_file, spec)
            return spec
        except Exception:
            continue
    pytest.fail(f"{pool_file}: no known scene has fingerprint {fp}")


@pytest.mark.parametrize("recipe", _recipes())
def test_no_evaluation_configuration_shares_poses_with_an_attack(recipe):
    d = RESULTS / recipe
    for pool_file in sorted((d / "pools").glob("*.json")):
        spec = _spec_of(pool_file)
        evaluation = load_pool(pool_file, spec)
        assert len(evaluation) >= 300
        for rec in sorted((d / "attack_configs").glob("*.json")):
            doc = json.loads(rec.read_text())
            trained = [e for part in ("attack", "validation") for e in doc[part]]
            # rebuild each recorded configuration from its seed: its content id must match the record,
            # so the poses compared below are the ones the attack used
            rebuilt = [sample_config(spec, e["seed"]) for e in trained]
            assert [config_id(c) for c in rebuilt] == [e["id"] for e in trained], rec.name
            poses = {pose_id(c) for c in rebuilt}
            assert not poses & {pose_id(c) for c in evaluation}, (
                f"{recipe}/{rec.name} shares poses with {pool_file.name}"
            )


def test_the_content_check_fails_on_an_overlap(tmp_path):
    """The same check on a record planted with an evaluation configuration's poses under another seed."""
    import dataclasses

    from attack.artifact import write_config_record
    from sim.configs import sample_pool

    spec = default_scene()
    evaluation = sample_pool(spec, 4, part="evaluation")
    planted = dataclasses.replace(evaluation[2], seed=123456789)
    write_config_record(tmp_path, sample_pool(spec, 3, part="attack") + [planted], [])
    assert overlap_count(evaluation, read_config_record(tmp_path)) == 1
