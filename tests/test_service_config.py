"""Service configuration: the documented example, environment overrides, clear refusals."""

from __future__ import annotations

from pathlib import Path

import pytest

from slamtka.service.config import ConfigError, config_from_dict, load_config

EXAMPLE = Path(__file__).resolve().parents[1] / "deploy" / "slamtka.example.toml"
MINIMAL = {"dicom": {"allowed_calling_ae_titles": ["CARM"]}, "carm": {"calibration": "cal.json"}}


def test_the_documented_example_loads_with_every_section():
    config = load_config(EXAMPLE, environ={})
    assert config.dicom.port == 11112 and config.dicom.allowed_calling_ae_titles == ["CARM_OR3"]
    assert [d.name for d in config.destinations] == ["or-display", "pacs"]
    assert config.destinations[1].tls and config.carm.kinematics["source_to_isocentre_mm"] == 620.0
    assert config.plans == Path("/var/lib/slamtka/plans") and config.source == EXAMPLE


def test_environment_overrides_scalars_with_types(tmp_path):
    env = {"SLAMTKA_DICOM_PORT": "11999", "SLAMTKA_DICOM_TLS_ENABLED": "false",
           "SLAMTKA_DATA_DIR": str(tmp_path), "SLAMTKA_PIPELINE_MIN_VIEW_SEPARATION_DEG": "20",
           "SLAMTKA_DICOM_ALLOWED_CALLING_AE_TITLES": "CARM_OR3, CARM_B", "SLAMTKA_UNRELATED": "x"}
    config = load_config(EXAMPLE, environ=env)
    assert config.dicom.port == 11999 and config.data_dir == tmp_path
    assert config.pipeline.min_view_separation_deg == 20.0
    # (the example binds CARM_OR3 to its address: a binding must name an allowed title)
    assert config.dicom.allowed_calling_ae_titles == ["CARM_OR3", "CARM_B"]


def test_relative_paths_are_relative_to_the_file(tmp_path):
    path = tmp_path / "svc.toml"
    path.write_text('data_dir = "data"\n[dicom]\nallowed_calling_ae_titles = ["C"]\n'
                    '[carm]\ncalibration = "cal/carm.json"\n')
    config = load_config(path, environ={})
    assert config.data_dir == tmp_path / "data" and config.carm.calibration == tmp_path / "cal/carm.json"
    assert config.spool_dir == tmp_path / "data" / "spool"


@pytest.mark.parametrize("change,message", [
    ({"dicom": {"allowed_calling_ae_titles": ["CARM"], "prot": 1}}, "dicom.prot: unknown key"),
    ({"dicom": {"allowed_calling_ae_titles": ["CARM"], "port": "104"}},
     "dicom.port: expected an integer"),
    ({"dicom": {"allowed_calling_ae_titles": ["CARM"], "port": 70000}}, "dicom.port: 70000 is outside"),
    ({"dicom": {"allowed_calling_ae_titles": []}}, "dicom.allowed_calling_ae_titles: list the C-arms"),
    ({"dicom": {"allowed_calling_ae_titles": ["BAD\\AE"]}}, "not a valid AE title"),
    ({"dicom": {"allowed_calling_ae_titles": ["CARM"], "tls": {"enabled": True}}},
     "dicom.tls.certificate: required when TLS is enabled"),
    ({"carm": {"calibration_match": "serial"}}, "carm.calibration_match: 'serial' must be"),
    ({"carm": {"calibration": "c", "kinematics": {"sid_nominal_mm": 5}}}, "carm.kinematics:"),
    ({"carm": {"calibration": "c", "setup": {"superior_carm": [0, 0, 1]}}}, "carm.setup:"),
    ({"destinations": [{"name": "x", "ae_title": "PACS", "host": "h", "objects": ["pdf"]}]},
     "destinations[0].objects"),
    ({"destinations": [{"name": "a", "ae_title": "A", "host": "h"},
                       {"name": "a", "ae_title": "B", "host": "h"}]}, "names must be unique"),
])
def test_bad_configuration_is_refused_naming_the_key(change, message):
    table = {**MINIMAL, **change}
    with pytest.raises(ConfigError) as err:
        config_from_dict(table, environ={})
    assert message in str(err.value)


def test_misspelt_environment_keys_and_bad_values_are_refused():
    with pytest.raises(ConfigError, match="SLAMTKA_DICOM_PROT: not a configuration key"):
        config_from_dict(MINIMAL, environ={"SLAMTKA_DICOM_PROT": "1"})
    with pytest.raises(ConfigError, match="SLAMTKA_DICOM_PORT .* is not a number"):
        config_from_dict(MINIMAL, environ={"SLAMTKA_DICOM_PORT": "eleven"})


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "none.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[dicom\nport = 1")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(bad)
