"""``--set key=value``: single config settings from the command line, typed by the config schema."""

import argparse

import pytest

from torchevtrack.camera import Camera
from torchevtrack.cli import main
from torchevtrack.cli.options import add_ablation_option, add_config_options, config_from_args
from torchevtrack.config import TrackerConfig
from torchevtrack.io.poses import read_tum
from torchevtrack.synth.generate import generate_sequence


def test_override_types_each_value_by_the_schema():
    cfg = TrackerConfig().override([
        "rate_hz=250", "ukf.enabled=true", "eros.kernel_size=9", "eros.decay=0.25", "template.rule=argmax",
        "velocity.feedback_axes=[vz, wy]", "render.decimate=500", "flow.max_speed=4000",
    ])
    assert cfg.rate_hz == 250.0 and isinstance(cfg.rate_hz, float)
    assert cfg.ukf.enabled is True and cfg.eros.kernel_size == 9 and cfg.eros.decay == 0.25
    assert cfg.template.rule == "argmax" and cfg.velocity.feedback_axes == ["vz", "wy"]
    assert cfg.render.decimate == 500 and cfg.flow.max_speed == 4000.0 and isinstance(cfg.flow.max_speed, float)
    assert cfg.override(["render.decimate=null"]).render.decimate is None
    assert cfg.override(["velocity.feedback_axes=wx,wz"]).velocity.feedback_axes == ["wx", "wz"]
    assert TrackerConfig().override(["ukf.p0=1e-2", "ukf.p0=2e-2"]).ukf.p0 == 0.02  # the last one wins
    # everything else keeps its value
    untouched = TrackerConfig().override(["ukf.enabled=true"]).to_dict()
    expected = TrackerConfig().to_dict()
    assert expected["ukf"]["enabled"] is False  # the default, so the override changes it
    expected["ukf"]["enabled"] = True
    assert untouched == expected


@pytest.mark.parametrize("assignment, message", [
    ("ukf.enabld=false", "unknown config key 'ukf.enabld': ukf has enabled, p0"),
    ("nope=1", "unknown config key 'nope': the config has burst, denoise, eros"),
    ("rate_hz.x=1", "rate_hz is not a section"),
    ("ukf=1", "is a section"),
    ("ukf.enabled=maybe", "config key 'ukf.enabled' expects bool, got 'maybe'"),
    ("eros.kernel_size=7.5", "expects int, got '7.5'"),
    ("eros.kernel_size=true", "expects int"),
    ("rate_hz=fast", "expects float"),
    ("velocity.feedback_axes=[1, 2]", "expects list[str]"),
    ("eros.decay=", "expects float"),
    ("ukf.enabled", "expects KEY=VALUE"),
    ("template.rule=best", "template.rule must be one of"),  # the schema's own checks still apply
])
def test_override_errors_are_one_line(assignment, message):
    with pytest.raises(ValueError, match=None) as e:
        TrackerConfig().override([assignment])
    assert message in str(e.value) and "\n" not in str(e.value)


@pytest.fixture(scope="module")
def seqdir(tmp_path_factory):
    root = tmp_path_factory.mktemp("set")
    generate_sequence("box", "regular", 0.02, seed=3, camera=Camera(160, 120, 125.6, 125.6, 79.5, 59.5),
                      progress=False).save(root / "seq")
    return root / "seq"


def test_track_applies_set_after_config(seqdir, tmp_path, capsys):
    yaml = tmp_path / "c.yaml"
    yaml.write_text("rate_hz: 250\nukf:\n  enabled: false\n")
    out = tmp_path / "p.txt"
    assert main(["track", str(seqdir), "--out", str(out), "--config", str(yaml), "--quiet"]) == 0
    t = read_tum(out)[0]
    assert len(t) >= 3 and set((t[1:] - t[:-1]).tolist()) == {4000}  # 250 Hz
    assert main(["track", str(seqdir), "--out", str(out), "--config", str(yaml), "--set", "rate_hz=1000",
                 "--quiet"]) == 0
    t = read_tum(out)[0]
    assert len(t) >= 12 and set((t[1:] - t[:-1]).tolist()) == {1000}  # --set wins over the file
    capsys.readouterr()


@pytest.mark.parametrize("command", ["track", "bench", "benchmark"])
def test_every_config_command_reports_a_bad_set_in_one_line(command, seqdir, tmp_path, capsys):
    target = seqdir.parent if command == "benchmark" else seqdir
    extra = ["--out", str(tmp_path / "o")] if command != "bench" else []
    assert main([command, str(target), *extra, "--set", "ukf.q=1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"torchevtrack {command}: error: unknown config key 'ukf.q': ukf has enabled, p0, q_p, q_pdot, " \
                  "q_q, q_w, r_p, r_q"
    assert not (tmp_path / "o").exists()  # nothing was written


def test_ablation_option_applies_after_the_config_and_only_when_given():
    p = argparse.ArgumentParser()
    add_config_options(p)
    add_ablation_option(p)
    assert config_from_args(p.parse_args([])) == TrackerConfig()  # no --ablation: the config as given
    assert config_from_args(p.parse_args(["--set", "ukf.enabled=true"])).ukf.enabled
    assert config_from_args(p.parse_args(["--ablation", "full"])) == TrackerConfig().replace(ukf={"enabled": True})
    # the ablation's own switches win over --set
    assert not config_from_args(p.parse_args(["--ablation", "no_ukf", "--set", "ukf.enabled=true"])).ukf.enabled
