"""Rig configuration: the packaged files load, and every kind of mistake is one line."""

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from rig.config import load_config, parse_config
from rig.errors import UsageError

ROOT = Path(__file__).resolve().parents[1]


def _good() -> dict:
    return yaml.safe_load((ROOT / "configs" / "rig-real.yaml").read_text())


@pytest.mark.parametrize("name", ["rig-sim.yaml", "rig-real.yaml"])
def test_example_configs_load(name):
    cfg = load_config(ROOT / "configs" / name)
    assert cfg.stage.driver == "sigma-koki"
    assert set(cfg.filter.positions) == {"r", "g", "b"}
    assert cfg.stage.allowed_range_deg[0] < cfg.stage.allowed_range_deg[1]


def test_default_is_packaged_sim_config():
    assert load_config().stage.port.startswith("sim-shot702://")


@pytest.mark.parametrize(
    "mutate, key",
    [
        (lambda d: d["stage"].update(driver="thorlabs-kinesis"), "stage.driver"),
        (lambda d: d["stage"].pop("port"), "stage.port"),
        (lambda d: d["stage"].update(speed_deg_s="fast"), "stage.speed_deg_s"),
        (lambda d: d["stage"].update(allowed_range_deg=[100, 10]), "stage.allowed_range_deg"),
        (lambda d: d["stage"].update(degrees_per_pulse=-1.0), "stage.degrees_per_pulse"),
        (lambda d: d["camera"].update(magnification=0), "camera.magnification"),
        (lambda d: d["filter"].update(positions={"r": 0}), "filter.positions"),
        (lambda d: d["filter"]["wavelengths_nm"].pop("g"), "filter.wavelengths_nm"),
        (lambda d: d["filter"].pop("port"), "filter.port"),
        (lambda d: d.pop("camera"), "camera"),
        (lambda d: d["stage"].update(sped=3), "stage.sped"),
        (lambda d: d.update(extra={}), "extra"),
    ],
)
def test_bad_config_names_file_and_key(mutate, key):
    d = _good()
    mutate(d)
    with pytest.raises(UsageError) as e:
        parse_config(d, "my-rig.yaml")
    msg = str(e.value)
    assert msg.startswith(f"my-rig.yaml: {key}"), msg
    assert "\n" not in msg


def test_cli_bad_config_one_line_exit_2(tmp_path):
    bad = tmp_path / "rig.yaml"
    bad.write_text("stage: [1, 2\n")
    r = subprocess.run([sys.executable, "-m", "rig.cli", "devices", "--config", str(bad)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "not valid YAML" in r.stderr
    assert "Traceback" not in r.stderr


@pytest.mark.parametrize("content, message", [
    (None, r"^where\.yaml: gone, pass another$"),
    (b"\xff\xfe not text", r"^where\.yaml: cannot read \(UnicodeDecodeError\); pass a readable YAML file$"),
    (b"a: [1, 2\nb: 3\n", r"^where\.yaml: line \d+: not valid YAML \("),
])
def test_a_yaml_file_that_cannot_be_read_is_one_line_in_the_callers_error(tmp_path, content, message):
    from rig.yaml_file import read_yaml

    class Mine(ValueError):
        pass

    p = tmp_path / "where.yaml"
    if content is not None:
        p.write_bytes(content)
    with pytest.raises(Mine, match=message) as e:
        read_yaml(p, "where.yaml", Mine, "gone, pass another")
    assert "\n" not in str(e.value)
    with pytest.raises(Mine, match=r"cannot read \(IsADirectoryError\)"):
        read_yaml(tmp_path, "where.yaml", Mine, "gone")
    p.write_text("stage: {port: x}\n", encoding="utf-8")
    assert read_yaml(p, "where.yaml", Mine, "gone") == {"stage": {"port": "x"}}
