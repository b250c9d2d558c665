"""Results written safely: untrusted text from bags, and an --out that holds results or is a trap."""
import json
import os

import numpy as np
import pytest

from offload_learner_py.offline.output import OutputDirError, code_block, prepare_out_dir, terminal_text, write_json


def test_untrusted_text_cannot_drive_a_terminal_or_close_a_code_fence():
    hostile = "/topic\x1b]0;owned\x07\x1b[2J```\n# injected"
    shown = terminal_text(hostile)
    assert "\x1b" not in shown and "\x07" not in shown and "\\x1b" in shown
    assert "```" not in code_block(hostile) and "\n" in code_block(hostile)


def test_out_dir_refuses_earlier_results_links_and_files(tmp_path):
    fresh = tmp_path / "fresh"
    assert prepare_out_dir(str(fresh)) == str(fresh) and fresh.is_dir()
    (fresh / "checkpoint.pt").write_bytes(b"earlier results")
    with pytest.raises(OutputDirError, match="--force"):
        prepare_out_dir(str(fresh))
    prepare_out_dir(str(fresh), force=True)
    link = tmp_path / "link"
    link.symlink_to(tmp_path / "elsewhere")
    with pytest.raises(OutputDirError, match="symbolic link"):
        prepare_out_dir(str(link), force=True)
    assert not (tmp_path / "elsewhere").exists()
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputDirError, match="is a file"):
        prepare_out_dir(str(tmp_path / "file"))
    with pytest.raises(OutputDirError, match="cannot create"):
        prepare_out_dir(str(tmp_path / "file" / "below"))


def test_retrain_and_report_refuse_to_overwrite_without_force(tmp_path, capsys):
    from offload_learner_py.offline import report, retrain
    out = tmp_path / "out"
    out.mkdir()
    (out / "evaluation.json").write_text("{}")
    for main in (retrain.main, report.main):
        assert main([str(tmp_path / "none.bag"), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert "--force" in err and err.count("\n") == 1
    assert os.listdir(out) == ["evaluation.json"]


def test_json_writer_turns_every_non_finite_number_into_null(tmp_path):
    path = tmp_path / "m.json"
    write_json(str(path), {"a": float("nan"), "b": [np.float64("-inf"), 1.5], "c": {"d": np.inf},
                                        "e": np.array([np.nan, 2.0]), "f": 3})
    assert json.loads(path.read_text(), parse_constant=lambda name: pytest.fail(f'non-strict JSON: {name}')) == {"a": None, "b": [None, 1.5], "c": {"d": None}, "e": [None, 2.0], "f": 3}
