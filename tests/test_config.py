
import pytest

from torchevtrack.config import ABLATIONS, DEFAULT_YAML, TrackerConfig



def test_default_yaml_spells_out_the_dataclass_defaults():
    assert TrackerConfig.from_yaml(DEFAULT_YAML) == TrackerConfig()


def test_partial_yaml_and_unknown_keys(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("rate_hz: 250\nukf:\n  enabled: false\n")
    cfg = TrackerConfig.from_yaml(f)
    assert cfg.rate_hz == 250.0 and cfg.period_us == 4000 and not cfg.ukf.enabled
    assert cfg.eros == TrackerConfig().eros
    f.write_text("ukf:\n  enabld: false\n")
    with pytest.raises(ValueError, match="unknown key"):
        TrackerConfig.from_yaml(f)
    with pytest.raises(FileNotFoundError):
        TrackerConfig.from_yaml(tmp_path / "missing.yaml")


@pytest.mark.parametrize("text, message", [
    ("template:\n  interior: 1.0\n  interior: 0.0\n", "'interior' given twice"),
    ("rate_hz: 250\nrate_hz: 500\n", "'rate_hz' given twice"),
    ("ukf: [unclosed\n", "c.yaml: while parsing"),
])
def test_a_key_given_twice_or_malformed_yaml_is_a_one_line_error(tmp_path, text, message):
    f = tmp_path / "c.yaml"
    f.write_text(text)
    with pytest.raises(ValueError, match=message) as e:
        TrackerConfig.from_yaml(f)
    assert "\n" not in str(e.value)


def test_invalid_values_are_rejected():
    with pytest.raises(ValueError, match="velocity.source"):
        TrackerConfig.from_dict({"velocity": {"source": "magic"}})
    with pytest.raises(ValueError, match="rate_hz"):
        TrackerConfig(rate_hz=0)
    for faces in (2, 1.5, True):  # a face count, checked before any mesh is loaded
        with pytest.raises(ValueError, match="render.decimate must be an integer face count"):
            TrackerConfig.from_dict({"render": {"decimate": faces}})
    assert TrackerConfig.from_dict({"render": {"decimate": 500}}).render.decimate == 500
    for speed in (0, -2.5, "fast", True):
        with pytest.raises(ValueError, match="template.max_depth_speed must be > 0"):
            TrackerConfig.from_dict({"template": {"max_depth_speed": speed}})
    assert TrackerConfig.from_dict({"template": {"max_depth_speed": float("inf")}}).template.max_depth_speed > 1e308


def test_ablations_change_only_their_switches():
    base = TrackerConfig()
    assert base.replace(**ABLATIONS["no_ukf"]) == base  # the default config is the paper's method without its UKF
    assert base.replace(**ABLATIONS["full"]) == base.replace(ukf={"enabled": True})
    assert all(base.replace(**ABLATIONS[m]).ukf.enabled for m in ("velocity_only", "correction_only", "hypotheses"))
    assert not base.replace(**ABLATIONS["velocity_only"]).template.enabled
    assert base.replace(**ABLATIONS["correction_only"]).velocity.source == "none"
    assert base.replace(**ABLATIONS["edopt_vel"]).velocity.source == "poses"


def test_unknown_correction_rule_is_an_error():
    with pytest.raises(ValueError, match="template.rule must be one of"):
        TrackerConfig.from_dict({"template": {"rule": "best"}})
    assert TrackerConfig.from_dict({"template": {"rule": "argmax"}}).template.rule == "argmax"
