"""Training configuration: files, overrides, typed errors."""

from __future__ import annotations

import json

import pytest

from tdfd.errors import InputError
from training.config import ConfigError, TrainConfig, apply_overrides, config_to_dict, load_config


def test_defaults_are_valid():
    cfg = load_config()
    assert isinstance(cfg, TrainConfig) and cfg.data.seed != cfg.data.val_seed


def test_toml_file_then_overrides(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text('out_dir = "runs/x"\n[optim]\nsteps = 10\nlr = 0.01\n[data]\nbatch_size = 4\n'
                 '[data.options]\nfamilies = ["plane"]\n')
    cfg = load_config(f, ["optim.lr=2e-3", "data.options.noise=0.5", "final_eval=false", "model.blocks=1"])
    assert cfg.out_dir == "runs/x" and cfg.optim.steps == 10 and cfg.optim.lr == 2e-3
    assert cfg.data.batch_size == 4 and cfg.data.options == {"families": ["plane"], "noise": 0.5}
    assert cfg.final_eval is False and cfg.model.blocks == 1


def test_context_accepts_one_side_or_a_list(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text("[model]\ncontext = 3\n")
    assert load_config(f).model.context == [3]
    assert load_config(None, ["model.context=[3, 7]"]).model.context == [3, 7]
    assert load_config(None, ["model.context=5"]).model.context == [5]
    assert load_config(None).model.context == []


def test_json_file_round_trip(tmp_path):
    cfg = load_config(None, ["seed=7"])
    f = tmp_path / "c.json"
    f.write_text(json.dumps(config_to_dict(cfg)))
    assert load_config(f) == cfg


@pytest.mark.parametrize("override,match", [
    ("optim.lrr=1", "unknown config key"),
    ("nosuch.key=1", "unknown config key"),
    ("optim.steps=1.5", "expected int"),
    ("optim.steps=ten", "expected int"),
    ("final_eval=maybe", "expected bool"),
    ("optim.lr=fast", "expected float"),
    ("data.options=[1]", "expected a mapping"),
    ("optim=3", "is a section"),
    ("optim.lr", "key=value"),
    ("optim.lr=-1", "must be > 0"),
    ("data.val_seed=0", "must differ"),
    ("device=tpu", "device"),
    ("model.context=[3, 4]", "model.context"),
    ("model.context=[3, 3]", "model.context"),
    ("model.context=[3, x]", "expected a list"),
    ("model.context=[3.5]", "expected int"),
    ("model.coarse=[1]", "coarse"),  # the removed experimental option is an unknown key
    ("calibration.pooled_planes=-1", "pooled_planes"),
    ("calibration.pooled_scenes=-2", "pooled_planes and pooled_scenes"),
])
def test_bad_overrides_raise_typed_errors(override, match):
    with pytest.raises(ConfigError, match=match) as info:
        load_config(None, [override])
    assert isinstance(info.value, InputError) and isinstance(info.value, ValueError)


def test_bad_files(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "missing.toml")
    bad = tmp_path / "c.toml"
    bad.write_text("optim = [")
    with pytest.raises(ConfigError, match="cannot parse"):
        load_config(bad)
    unk = tmp_path / "u.json"
    unk.write_text('{"optim": {"momentum": 0.9}}')
    with pytest.raises(ConfigError, match="optim.momentum"):
        load_config(unk)
    wrong = tmp_path / "w.json"
    wrong.write_text('{"optim": {"steps": "many"}}')
    with pytest.raises(ConfigError, match="optim.steps"):
        load_config(wrong)
    txt = tmp_path / "c.txt"
    txt.write_text("")
    with pytest.raises(ConfigError, match=".json, .toml"):
        load_config(txt)


def test_overrides_do_not_mutate_input():
    cfg = TrainConfig()
    new = apply_overrides(cfg, ["optim.steps=5", "data.options.x=1"])
    assert cfg.optim.steps != 5 and cfg.data.options == {} and new.data.options == {"x": 1}


def test_cli_rejects_bad_key(capsys):
    from training.__main__ import main

    with pytest.raises(SystemExit) as info:
        main(["--set", "optim.nope=1"])
    assert info.value.code == 2
    assert "unknown config key" in capsys.readouterr().err
    assert main(["--print-config", "--set", "optim.steps=3"]) == 0
    assert json.loads(capsys.readouterr().out)["optim"]["steps"] == 3
