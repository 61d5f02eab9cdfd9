"""``advobj experiment``'s options turned into what a recipe runs with, in one place
(:func:`trials.cli.experiment.experiment_config`): the command runs with the config and targets that
:func:`~trials.cli.experiment.parse_experiment` gives for the same words (what ``tools/evidence.py
retable`` rebuilds a committed table with), and a malformed value is one line naming its flag."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from typer._click.exceptions import ClickException

from trials.cli import experiment
from trials.cli.experiment import CONFIG_OPTIONS, experiment_config, experiment_targets, parse_experiment
from trials.cli.main import main
from trials.cli.options import OptionError, name_list
from trials.experiments.recipes import PRESETS, TABLE2_ROWS, TRANSFER_TARGETS, ExperimentError, resolve_experiment


def _ran_with(monkeypatch, argv):
    """The config and targets ``advobj ARGV`` hands to the recipe (the recipe itself is not run)."""
    seen = []

    def fake_run(name, cfg, out, policy, targets, *a, **k):
        seen.append((cfg, targets))
        raise SystemExit(0)

    with monkeypatch.context() as m:
        m.setattr(experiment, "run_experiment", fake_run)
        m.setattr("sys.argv", ["advobj", *argv])
        with pytest.raises(SystemExit) as e:
            main()
    assert e.value.code == 0
    (ran,) = seen
    return ran


COMMANDS = [
    ["table1", "--preset", "quick"],
    ["table1", "--preset", "paper", "--episodes", "7", "--iterations", "3", "--attack-seeds", "0,2"],
    ["table1", "--pool", "pools/p.json", "--device", "cuda", "--min-clean-success", "0.25"],
    ["table2", "--rows", f" {TABLE2_ROWS[1][0]}, {TABLE2_ROWS[0][0]},", "--attack-seeds", "4"],
    ["transfer", "--archs", "vgg16, resnet34", "--target", "vgg16=runs/v", "--target", "resnet34=runs/r.onnx"],
    ["lighting", "--episodes", "1", "--min-clean-success", "0"],
]


@pytest.mark.parametrize("args", COMMANDS, ids=[" ".join(a) for a in COMMANDS])
def test_a_command_runs_with_the_config_and_targets_its_words_parse_to(monkeypatch, tmp_path, args):
    cfg, targets = _ran_with(monkeypatch, ["experiment", *args, "--out", str(tmp_path / "out")])
    parsed, params = parse_experiment(args[0], args[1:])
    assert parsed == cfg and experiment_targets(params["target"]) == targets


def test_the_options_reach_the_config_as_the_recipes_read_them():
    cfg = experiment_config(
        "quick",
        episodes=7,
        pool="pools/p.json",
        device="cuda",
        archs=" vgg16,, resnet34 ",
        iterations=3,
        attack_seeds="2,0",
        rows="c2f_untargeted,ns",
        min_clean_success=0.5,
    )
    assert (cfg.episodes, cfg.pool, cfg.device) == (7, "pools/p.json", "cuda")
    assert cfg.transfer_targets == ("vgg16", "resnet34") and cfg.rows == ("c2f_untargeted", "ns")
    assert cfg.attack_overrides == {"iterations": 3} and cfg.attack_seeds == (2, 0) and cfg.min_clean_success == 0.5


def test_options_not_given_keep_the_presets_values():
    for preset in PRESETS:
        assert experiment_config(preset) == resolve_experiment(preset)


def test_the_config_options_are_the_commands_own_parameters():
    _, params = parse_experiment("table1", [])
    assert set(CONFIG_OPTIONS) < set(params) and CONFIG_OPTIONS[0] == "preset"


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(min_value=0, max_value=2**63), min_size=1, max_size=5, unique=True))
def test_any_distinct_attack_seeds_parse_as_given(seeds):
    text = ",".join(str(s) for s in seeds)
    cfg, _ = parse_experiment("table1", ["--attack-seeds", text])
    assert cfg.attack_seeds == tuple(seeds) == experiment_config("quick", attack_seeds=text).attack_seeds


_NAME = st.text(st.characters(whitelist_categories=("L", "Nd"), whitelist_characters="_-."), min_size=1, max_size=8)
_PADS = st.lists(st.sampled_from(["", " ", "  "]), min_size=10, max_size=10)


def _padded(names, pads) -> str:
    """``names`` joined by commas, each padded with spaces, with empty or blank items at both ends."""
    return pads[0] + "," + ",".join(f"{pads[i + 1]}{n}{pads[-i - 1]}" for i, n in enumerate(names)) + "," + pads[5]


@settings(max_examples=60, deadline=None)
@given(st.lists(_NAME, min_size=1, max_size=4), _PADS)
def test_comma_separated_names_parse_stripped_with_empty_items_dropped(names, pads):
    assert name_list(_padded(names, pads)) == tuple(names)


@settings(max_examples=30, deadline=None)
@given(
    st.lists(st.sampled_from(TRANSFER_TARGETS), min_size=1, unique=True),
    st.lists(st.sampled_from([row[0] for row in TABLE2_ROWS]), min_size=1, max_size=4, unique=True),
    _PADS,
)
def test_archs_and_rows_reach_the_config_as_their_names(archs, rows, pads):
    cfg = experiment_config("quick", archs=_padded(archs, pads), rows=_padded(rows, pads))
    assert cfg.transfer_targets == tuple(archs) and cfg.rows == tuple(rows)


def test_no_names_is_none_and_only_commas_or_blanks_are_no_names():
    assert name_list(None) is None
    assert name_list("") == name_list(" , ,") == ()


@pytest.mark.parametrize(
    "args, error, flag",
    [
        (["--attack-seeds", "0,x"], OptionError, "--attack-seeds"),
        (["--attack-seeds", ""], OptionError, "--attack-seeds"),
        (["--attack-seeds", "0,0"], ExperimentError, "attack_seeds"),
        (["--preset", "huge"], ExperimentError, "preset"),
    ],
)
def test_a_malformed_value_is_one_line_naming_its_flag_or_field(args, error, flag):
    with pytest.raises(error) as e:
        parse_experiment("table1", args)
    assert flag in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("target", [["vgg16"], ["=runs/v"], ["vgg16=a", "vgg16=b"]])
def test_a_malformed_or_repeated_target_is_one_line_naming_the_flag(target):
    with pytest.raises(OptionError, match="--target"):
        experiment_targets(target)


@pytest.mark.parametrize("args", [["--episodes", "zero"], ["--episodes", "0"], ["--no-such-flag"]])
def test_words_the_command_refuses_do_not_parse(args):
    with pytest.raises(ClickException):
        parse_experiment("table1", args)
