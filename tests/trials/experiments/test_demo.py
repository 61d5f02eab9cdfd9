"""The demo's orchestration on a tiny budget (the reference policy stubbed by a tiny checkpoint)."""

import pytest

from tests.trials.conftest import MAX_STEPS


@pytest.mark.slow
def test_demo_writes_report_with_table_plots_and_gifs(tmp_path, monkeypatch, tiny_policy_dir, pool_file):
    import trials.experiments.demo as demo
    import trials.experiments.recipes as ex

    monkeypatch.setattr(
        demo,
        "DEMO_BUDGET",
        dict(
            attack_overrides={"iterations": 1, "num_envs": 1, "rollout_steps": 1, "texture_size": 8},
            episodes=2,
            max_steps=MAX_STEPS,
            num_envs=2,
            gifs=1,
            pool=str(pool_file),
        ),
    )
    for mod in (ex, demo):  # demo binds ensure_policy at import
        monkeypatch.setattr(mod, "ensure_policy", lambda ctx, name="reference", **kw: tiny_policy_dir)
    result = demo.run_demo(tmp_path, log=lambda m: None)
    report = (tmp_path / "report.md").read_text()
    assert "| 3D Object | ours |" in report and "| 2D Patch | paper |" in report
    assert "](evals/demo/bars_by_phi.png)" in report and (tmp_path / "evals" / "demo" / "bars_by_phi.png").is_file()
    assert "compare_clean_vs_attack" in report and (tmp_path / "scene.png").is_file()
    s = result["summary"]["conditions"]
    assert set(s) == {"clean", "attack", "patch"} and s["attack"]["n"] == 2
