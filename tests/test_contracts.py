"""The n2d.json manifest and atomic stage directories: complete only when finished, nothing lost on failure."""

import json

import pytest

from n2d_common.contracts import MANIFEST, atomic_write_json, open_stage, read_manifest, stage_output
from n2d_common.errors import ContractError


def _write(out, kind="model", payload="v1", **kw):
    with stage_output(out, kind, **kw) as w:
        (w.path / "data.txt").write_text(payload)
        w.finish(config={"a": 1}, inputs={"session": "/x"})


def test_finished_stage_is_complete_and_readable(tmp_path):
    out = tmp_path / "model"
    _write(out)
    manifest = open_stage(out, "model")
    assert manifest["complete"] and manifest["kind"] == "model" and manifest["version"] == 1
    assert manifest["inputs"] == {"session": "/x"} and manifest["config"] == {"a": 1}
    assert not (tmp_path / "model.partial").exists()


def test_crash_leaves_no_complete_looking_output_and_resumes(tmp_path):
    out = tmp_path / "ds"
    with pytest.raises(RuntimeError), stage_output(out, "dataset", config={"frames": 4}) as w:
        (w.path / "frame0").write_text("done")
        raise RuntimeError("killed")
    assert not out.exists()
    with pytest.raises(ContractError, match="--resume"):
        open_stage(out, "dataset")
    assert read_manifest(tmp_path / "ds.partial")["complete"] is False
    with stage_output(out, "dataset", config={"frames": 4}) as w:
        assert w.resumed and (w.path / "frame0").read_text() == "done"
        w.finish()
    assert open_stage(out, "dataset")["complete"]


def test_partial_of_another_job_is_refused_unless_overwrite(tmp_path):
    out = tmp_path / "ds"
    with pytest.raises(RuntimeError), stage_output(out, "dataset", config={"frames": 4}):
        raise RuntimeError
    with pytest.raises(ContractError, match="another job"):
        with stage_output(out, "dataset", config={"frames": 8}):
            pass
    with stage_output(out, "dataset", config={"frames": 8}, overwrite=True) as w:
        assert not w.resumed
        w.finish()


def test_existing_output_is_refused_and_survives_failed_overwrite(tmp_path):
    out = tmp_path / "model"
    _write(out, payload="old")
    with pytest.raises(ContractError, match="already exists"):
        _write(out, payload="new")
    with pytest.raises(RuntimeError), stage_output(out, "model", overwrite=True) as w:
        (w.path / "data.txt").write_text("half")
        raise RuntimeError
    assert (out / "data.txt").read_text() == "old"
    _write(out, payload="new", overwrite=True)
    assert (out / "data.txt").read_text() == "new"


def test_foreign_and_wrong_kind_directories_are_refused(tmp_path):
    foreign = tmp_path / "photos"
    foreign.mkdir()
    (foreign / "img.jpg").write_bytes(b"x")
    with pytest.raises(ContractError, match="not an n2d directory"):
        _write(foreign)
    assert (foreign / "img.jpg").read_bytes() == b"x"
    with pytest.raises(ContractError, match="no n2d.json"):
        open_stage(foreign, "capture_session")
    out = tmp_path / "model"
    _write(out)
    with pytest.raises(ContractError, match="is a model, not a dataset"):
        open_stage(out, "dataset")
    with pytest.raises(ContractError, match="does not exist"):
        open_stage(tmp_path / "missing", "model")


def test_corrupt_and_newer_manifests(tmp_path):
    out = tmp_path / "model"
    _write(out)
    data = json.loads((out / MANIFEST).read_text())
    atomic_write_json(out / MANIFEST, {**data, "version": 99})
    with pytest.raises(ContractError, match="newer n2d"):
        open_stage(out, "model")
    (out / MANIFEST).write_text("{not json")
    with pytest.raises(ContractError, match="corrupt"):
        open_stage(out, "model")


@pytest.mark.parametrize("edit", [{"kind": 7}, {"version": "one"}, {"version": 1.5}, {"config": [1]}])
def test_manifest_fields_of_another_type_are_refused(tmp_path, edit):
    out = tmp_path / "model"
    _write(out)
    manifest = json.loads((out / MANIFEST).read_text())
    (out / MANIFEST).write_text(json.dumps(manifest | edit))
    with pytest.raises(ContractError) as err:
        open_stage(out, "model")
    assert err.value.hint


def test_bad_input_found_before_any_kept_work_leaves_nothing(tmp_path):
    from n2d_common.contracts import discard_on_bad_input

    out = tmp_path / "dope"
    with pytest.raises(ContractError), stage_output(out, "dope_model") as w, discard_on_bad_input(w, "ckpt"):
        raise ContractError("a damaged frame", "regenerate the dataset")
    assert not out.exists() and not (tmp_path / "dope.partial").exists()
    with pytest.raises(ContractError), stage_output(out, "dope_model") as w, discard_on_bad_input(w, "ckpt"):
        (w.path / "ckpt").write_text("step 3")
        raise ContractError("a damaged frame", "regenerate the dataset")
    assert (tmp_path / "dope.partial" / "ckpt").read_text() == "step 3"  # kept work stays for a resume


def test_a_write_killed_half_way_leaves_nothing_in_the_output(tmp_path):
    """kill -9 during an atomic write leaves its temporary file (no handler runs); resuming and finishing remove it,
    so the published directory holds only what the stage wrote."""
    out = tmp_path / "ds"
    with pytest.raises(RuntimeError), stage_output(out, "dataset", config={"frames": 2}) as w:
        (w.path / "rgb").mkdir()
        (w.path / "rgb" / ".000001.png.k2j4x.tmp").write_bytes(b"half a frame")  # what the killed write left
        raise RuntimeError("killed")
    with stage_output(out, "dataset", config={"frames": 2}) as w:
        assert w.resumed and not any(w.path.rglob("*.tmp"))
        (w.path / "rgb" / ".000002.png.q8d1m.tmp").write_bytes(b"another")  # a writer thread killed later
        atomic_write_json(w.path / "rgb" / "000001.json", {})
        w.finish()
    assert sorted(p.name for p in out.rglob("*") if p.is_file()) == ["000001.json", MANIFEST]
