"""Bad input, round two (issue 30): sizes that cannot fit or cannot finish are refused before any
work, naming the key and what was expected; study storages that cannot be opened are one line."""

from __future__ import annotations

import json

import pytest
from helpers import run_cli

from virus_nerf.errors import ConfigError, UsageError


@pytest.mark.parametrize("doc, fragment", [
    ({"march": {"near": 1e9}}, "march.near 1000000000.0: expected a finite number in [0, 100]"),
    ({"march": {"step_size": 1e-12}}, "march.step_size 1e-12: expected a finite number >= 0.0001"),
    ({"field": {"density_clamp": 1e300}}, "field.density_clamp 1e+300: expected a finite number in (0, 80]"),
    ({"evaluation": {"n_rays": 10**9}}, "evaluation.n_rays 1000000000: expected an integer in [1, 1000000]"),
])
def test_config_values_that_never_finish_are_refused(tmp_path, doc, fragment):
    from virus_nerf.config_io import load_json_config
    from virus_nerf.trainer.config import TrainConfig

    path = tmp_path / "c.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(ConfigError) as exc:
        load_json_config(TrainConfig, path)
    assert fragment in str(exc.value)


def test_a_grid_that_cannot_fit_is_refused_with_the_memory_it_needs():
    import torch

    from virus_nerf.engine.model import build_grid
    from virus_nerf.grid.virus import VirusGridConfig
    from virus_nerf.scene_box import SceneBox
    from virus_nerf.trainer.config import TrainConfig
    from virus_nerf.utils.memory import require_memory

    cfg = TrainConfig(virus_grid=VirusGridConfig(max_resolution=100_000))
    with pytest.raises(UsageError, match=r"virus_grid.max_resolution: a 100000x50000x25000 cell grid: would need "
                                         r"\d+\.\d GiB"):
        build_grid(cfg, SceneBox((0, 0, 0), (10, 5, 2.5)), torch.device("cpu"))
    require_memory("x", 2**30, "less", limit=4 * 2**30)  # half the limit or less: fine
    with pytest.raises(UsageError, match=r"x: would need 3.0 GiB and this machine has 4.0 GiB; expected less"):
        require_memory("x", 3 * 2**30, "less", limit=4 * 2**30)


def test_study_storages_that_cannot_be_opened_are_one_line(sample_dir, tmp_path):
    pytest.importorskip("optuna")
    (tmp_path / "folder").mkdir()
    (tmp_path / "bad.journal").write_bytes(b"garbage\x00\xff{not json\n")
    for storage, fragment in (("foo://bar", "cannot open study 's1' there (NoSuchModuleError"),
                              (f"sqlite:///{tmp_path / 'folder'}", "cannot open study 's1' there (OperationalError"),
                              (str(tmp_path / "bad.journal"), "not a readable Optuna journal"),
                              (str(tmp_path / "folder"), "is a folder; expected a journal file")):
        code, _, err = run_cli(["tune", "--data", sample_dir, "--room", "office", "--study", "s1", "--trials", "0",
                                "--storage", storage, "--out", tmp_path / "out"])
        assert code == 2 and len(err.strip().splitlines()) == 1 and fragment in err, err
        assert not (tmp_path / "out").exists()  # the --out this call made (study.json) goes with it
    (tmp_path / "note.txt").write_text("x")
    for flag, path in (("--out", tmp_path / "note.txt" / "sub"), ("--export-config", tmp_path / "note.txt" / "b.json")):
        args = ["tune", "--data", sample_dir, "--room", "office", "--study", "s2", "--trials", "0",
                "--out", tmp_path / "out2", flag, path]
        code, _, err = run_cli(args[:-4] + args[-2:] if flag == "--out" else args)
        assert code == 2 and err == f"virus-nerf: error: {flag} {path}: cannot be made: {tmp_path / 'note.txt'} is a " \
            "file, not a folder\n", err
        assert not (tmp_path / "out2").exists()
