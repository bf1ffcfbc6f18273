"""Every user mistake in a config file is a one-line error naming the file and the key and
what was expected; types are checked, not coerced."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from virus_nerf.config_io import from_dict, load_json_config, to_dict
from virus_nerf.errors import ConfigError, UsageError
from virus_nerf.trainer.config import TrainConfig


# ------------------------------------------------------------------------------ config files
def write_config(tmp_path: Path, doc) -> Path:
    p = tmp_path / "cfg.json"
    p.write_text(json.dumps(doc) if not isinstance(doc, str) else doc)
    return p


@pytest.mark.parametrize(
    "doc, fragment",
    [
        ({"online": "false"}, "key 'online': expected a JSON bool (true or false), got string \"false\""),
        ({"online": 0}, "key 'online': expected a JSON bool (true or false), got int 0"),
        ({"batch_size": "2048"}, "key 'batch_size': expected an integer, got string \"2048\""),
        ({"batch_size": 20.5}, "key 'batch_size': expected an integer, got float 20.5"),
        ({"batch_size": True}, "key 'batch_size': expected an integer, got bool true"),
        ({"max_steps": "5"}, "key 'max_steps': expected an integer or null, got string \"5\""),
        ({"max_time": "10"}, "key 'max_time': expected a number or null, got string \"10\""),
        ({"grid": "voxel"}, "key 'grid': expected one of \"virus\", \"ngp\", got string \"voxel\""),
        ({"sensors": "camera"}, "key 'sensors': expected a list, got string \"camera\""),
        ({"sensors": ["camera", 3]}, "key 'sensors[1]': expected a string, got int 3"),
        ({"optim": {"betas": [0.9, "x"]}}, "key 'optim.betas[1]': expected a number, got string \"x\""),
        ({"optim": {"betas": [0.9]}}, "key 'optim.betas': expected a list of 2 values, got 1"),
        ({"optim": 3}, "key 'optim': expected a JSON object with the keys of OptimConfig, got int 3"),
        ({"evaluation": {"zones": [{"name": "z", "lo": "0", "hi": 1}]}}, "key 'evaluation.zones[0].lo': expected a number"),
        ({"march": {"stepsize": 0.1}}, "key 'march': unknown key(s) ['stepsize'] (did you mean 'step_size'?)"),
        ({"bogus": 1}, "unknown key(s) ['bogus']"),
        ({"max_steps": 0}, "max_steps 0: expected an integer >= 1"),
        ({"batch_size": -1}, "batch_size -1: expected an integer >= 1"),
        ({"march": {"step_size": 0}}, "march.step_size 0.0: expected a finite number > 0"),
        ({"virus_grid": {"update_interval": 0}}, "key 'virus_grid': VirusGridConfig: invalid value for update_interval"),
        ({"max_steps": None, "max_time": None}, "set max_steps or max_time"),
        ({"device": "tpu"}, "device 'tpu': expected 'auto', 'cpu', 'cuda'"),
        ([1, 2], "expected a JSON object with the keys of TrainConfig, got list [1, 2]"),
        ("{not json", "not valid JSON: Expecting property name enclosed in double quotes at line 1 column 2"),
        ('{"max_time": NaN}', "key 'max_time': expected a number or null, got float NaN"),
    ],
)
def test_config_file_errors_name_file_and_key(tmp_path, doc, fragment):
    path = write_config(tmp_path, doc)
    with pytest.raises(ConfigError) as exc:
        load_json_config(TrainConfig, path)
    assert str(exc.value).startswith(str(path)) and fragment in str(exc.value)
    assert isinstance(exc.value, ValueError) and "\n" not in str(exc.value)


def test_missing_config_file(tmp_path):
    with pytest.raises(ConfigError, match="nope.json: config file not found"):
        load_json_config(TrainConfig, tmp_path / "nope.json")


def test_config_types_that_are_accepted():
    cfg = from_dict(TrainConfig, {"batch_size": 2048.0, "max_time": 10, "online": False,
                                  "optim": {"betas": [1, 0.5]}, "sensors": ["camera", "irs"]})
    assert cfg.batch_size == 2048 and type(cfg.batch_size) is int
    assert cfg.max_time == 10.0 and type(cfg.max_time) is float
    assert cfg.optim.betas == (1.0, 0.5) and cfg.sensors == ("camera", "irs")
    assert from_dict(TrainConfig, json.loads(json.dumps(to_dict(cfg)))) == cfg
    with pytest.raises(ConfigError, match=r"^config\.march: unknown key\(s\) \['stepsize'\]"):
        from_dict(TrainConfig, {"march": {"stepsize": 0.1}})


def test_train_config_checks_types_and_ranges_itself():
    for bad, fragment in [(dict(batch_size=0), "batch_size 0"), (dict(max_steps=0), "max_steps 0"),
                          (dict(max_time=0.0), "max_time 0.0"), (dict(online="false"), "online 'false'"),
                          (dict(batch_size="2048"), "batch_size '2048'"), (dict(seed=-1), "seed -1"),
                          (dict(image_scale=0.0), "image_scale 0.0"), (dict(playback_speed=0.0), "playback_speed")]:
        with pytest.raises(ValueError, match=fragment.replace("(", r"\(")):
            TrainConfig(**bad)


def test_usage_error_is_a_value_error():
    assert issubclass(UsageError, ValueError) and issubclass(ConfigError, UsageError)
