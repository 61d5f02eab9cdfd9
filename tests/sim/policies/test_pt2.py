""".pt2 ExportedPrograms as white-box policies: the card inside, and what loading guarantees.

Each file is written here by torch.export.save from a tiny policy of the zoo; the hostile ones are
that file with one entry of its archive changed, so each check is shown to be what refuses it.
"""

from __future__ import annotations

import io
import json
import pickle
import zipfile

import numpy as np
import pytest
import torch

from sim.policies.checkpoint import load_policy
from sim.policies.graph_policy import GraphPolicy
from sim.policies.interface import PolicyError
from sim.policies.pt2 import CARD_ENTRY, export_pt2, load_pt2
from tests.policy_zoo import card_of, contract_of, tiny_policy

CONTRACTS = {
    "image-delta": contract_of((), ("delta_tcp", 1, 1)),
    "state-absolute-K3": contract_of(("tcp_pose", "gripper"), ("absolute_tcp", 3, 3)),
}


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    d = tmp_path_factory.mktemp("pt2")
    p = tiny_policy(CONTRACTS["state-absolute-K3"])
    return p, export_pt2(p, d / "p.pt2", card_of(p))


@pytest.mark.parametrize("name", sorted(CONTRACTS))
def test_a_pt2_loads_white_box_and_computes_the_checkpoint(tmp_path, name):
    p = tiny_policy(CONTRACTS[name])
    path = export_pt2(p, tmp_path / "p.pt2", card_of(p))
    g = load_policy(path)
    assert isinstance(g, GraphPolicy) and g.white_box and g.format == "pt2"
    assert g.contract == p.contract and g.card.arch == p.config and g.image_size == 32
    x = torch.rand(5, 3, 32, 32)
    st = torch.rand(5, p.contract.state_dim) if p.contract.state_dim else None
    torch.testing.assert_close(g.features(x), p.features(x))  # cut where the checkpoint's Grad-CAM reads
    torch.testing.assert_close(g(x, st), p(x, st))
    images = np.random.default_rng(0).integers(0, 256, (3, 32, 32, 3), dtype=np.uint8)
    s = None if st is None else st[:3].numpy()
    np.testing.assert_allclose(g.act(images, s), p.act(images, s), atol=1e-6)


def test_the_export_leaves_no_path_of_the_exporting_machine_in_the_file(exported):
    _, path = exported
    with zipfile.ZipFile(path) as z:
        model = z.read(next(n for n in z.namelist() if n.endswith("models/model.json"))).decode()
        card = json.loads(z.read(next(n for n in z.namelist() if n.endswith(CARD_ENTRY))))
    assert "stack_trace" not in model and "site-packages" not in model
    assert card["feature_map"] and card["contract"]["action"]["chunk"] == 3


def _rewrite(src, dst, change):
    """Copy the archive ``src`` to ``dst`` entry by entry; ``change(name, data)`` returns new bytes
    (or None to drop the entry)."""
    with zipfile.ZipFile(src) as z, zipfile.ZipFile(dst, "w", zipfile.ZIP_STORED) as out:
        for info in z.infolist():
            data = change(info.filename, z.read(info.filename))
            if data is not None:
                out.writestr(info.filename, data)
    return dst


def test_a_copy_rewritten_entry_by_entry_still_loads(exported, tmp_path):
    """The control for the hostile files below: rewriting the archive alone refuses nothing."""
    p, path = exported
    g = load_pt2(_rewrite(path, tmp_path / "copy.pt2", lambda n, d: d))
    x, st = torch.rand(2, 3, 32, 32), torch.rand(2, 7)
    torch.testing.assert_close(g(x, st), p(x, st))


def _one_line(path, match):
    with pytest.raises(PolicyError, match=match) as err:
        load_pt2(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)
    return str(err.value)


def test_garbage_and_truncated_files_are_one_line(exported, tmp_path):
    _, path = exported
    (tmp_path / "garbage.pt2").write_bytes(b"PK\x03\x04" + bytes(range(256)) * 4)
    _one_line(tmp_path / "garbage.pt2", "not a torch.export archive")
    data = path.read_bytes()
    (tmp_path / "half.pt2").write_bytes(data[: len(data) // 2])
    _one_line(tmp_path / "half.pt2", "not a torch.export archive")
    (tmp_path / "empty.pt2").write_bytes(b"")
    _one_line(tmp_path / "empty.pt2", "not a torch.export archive")


@pytest.mark.parametrize(
    "entry, new",
    [
        ("archive_version", b"1"),  # the archive format of a later torch
        ("models/model.json", "schema"),  # the program schema of another torch
    ],
)
def test_a_file_exported_by_an_incompatible_torch_is_one_line(exported, tmp_path, entry, new):
    _, path = exported

    def change(name, data):
        if not name.endswith(entry):
            return data
        if new == "schema":
            doc = json.loads(data)
            doc["schema_version"] = {"major": 99, "minor": 0}
            doc["torch_version"] = "9.9.0"
            return json.dumps(doc).encode()
        return new

    msg = _one_line(_rewrite(path, tmp_path / "other.pt2", change), "exported by an incompatible torch")
    assert torch.__version__ in msg


def _model_change(edit):
    def change(name, data):
        if not name.endswith("models/model.json"):
            return data
        doc = json.loads(data)
        edit(doc)
        return json.dumps(doc).encode()

    return change


class _Marker:
    """Unpickling this object creates ``path``: the proof a pickle was loaded."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def test_pickled_weights_are_never_unpickled(exported, tmp_path):
    _, path = exported
    marker = tmp_path / "unpickled"

    def change(name, data):
        if name.endswith("data/weights/model_weights_config.json"):
            doc = json.loads(data)
            first = next(iter(doc["config"].values()))
            first["use_pickle"] = True
            return json.dumps(doc).encode()
        if name.endswith("data/weights/weight_0"):
            return pickle.dumps(_Marker(marker))
        return data

    _one_line(_rewrite(path, tmp_path / "pickled.pt2", change), "stored as a pickle")
    assert not marker.exists()


def test_example_inputs_that_are_not_plain_tensors_are_refused_not_unpickled(exported, tmp_path):
    _, path = exported
    marker = tmp_path / "unpickled"
    buf = io.BytesIO()
    torch.save(_Marker(marker), buf)

    def change(name, data):
        return buf.getvalue() if name.endswith("data/sample_inputs/model.pt") else data

    _one_line(_rewrite(path, tmp_path / "inputs.pt2", change), "example inputs are not plain tensors")
    assert not marker.exists()


def test_a_node_target_outside_aten_is_refused(exported, tmp_path):
    def edit(doc):
        doc["graph_module"]["graph"]["nodes"][0]["target"] = "torch.hub.load"

    _one_line(_rewrite(exported[1], tmp_path / "hub.pt2", _model_change(edit)), "'torch.hub.load' is not an ATen")


def test_a_symbolic_shape_that_is_python_is_refused(exported, tmp_path):
    marker = tmp_path / "evaluated"

    def edit(doc):
        values = doc["graph_module"]["graph"]["tensor_values"]
        values["x"]["sizes"][0]["as_expr"]["expr_str"] = f"__import__('pathlib').Path('{marker}').touch()"

    _one_line(_rewrite(exported[1], tmp_path / "sympy.pt2", _model_change(edit)), "symbolic shape")
    assert not marker.exists()


def test_a_parameter_name_that_would_be_code_is_refused(exported, tmp_path):
    def edit(doc):
        spec = next(s for s in doc["graph_module"]["signature"]["input_specs"] if "parameter" in s)
        spec["parameter"]["parameter_name"] = 'w") or print("owned'

    _one_line(_rewrite(exported[1], tmp_path / "name.pt2", _model_change(edit)), "not letters, digits")


def test_guard_code_in_the_file_is_never_run(exported, tmp_path):
    p, path = exported
    marker = tmp_path / "guarded"

    def edit(doc):
        doc["guards_code"] = [f"__import__('pathlib').Path('{marker}').touch() is None"]

    g = load_pt2(_rewrite(path, tmp_path / "guards.pt2", _model_change(edit)))
    g(torch.rand(2, 3, 32, 32), torch.rand(2, 7))
    assert not marker.exists()


def test_compiled_code_and_unknown_entries_are_refused(exported, tmp_path):
    _, path = exported
    root = zipfile.ZipFile(path).namelist()[0].split("/")[0]

    def add(entry):
        def change(name, data):
            return data

        dst = _rewrite(path, tmp_path / f"{entry.replace('/', '_')}.pt2", change)
        with zipfile.ZipFile(dst, "a", zipfile.ZIP_STORED) as z:
            z.writestr(f"{root}/{entry}", b"\x7fELF")
        return dst

    _one_line(add("data/aotinductor/model/model.so"), "AOTInductor")
    _one_line(add("data/weights/model.pt"), "unexpected archive entry")


def test_a_card_that_disagrees_with_the_program_is_one_line(tmp_path):
    p = tiny_policy(CONTRACTS["image-delta"])
    card = card_of(p).model_copy(update={"contract": CONTRACTS["state-absolute-K3"]})
    path = export_pt2(p, tmp_path / "p.pt2", card)
    _one_line(path, "no state input")
