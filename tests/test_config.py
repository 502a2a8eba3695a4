"""Scanner configuration: the task's defaults and Configuration.ini parsing."""

import dataclasses

import pytest

from octcl.config import DEFAULT_CONFIG, ConfigError, ScannerConfig

OFFICIAL_INI = """\
[Parameters]
scan filename = Scan_Exp1_Uniform_A.png
scatterers coordinates file = Phantom_Exp1_Uniform_A.txt
a-scan pixel numbers = 256
vertical pixel size mcm = 6.0
central wavelength mcm = 1.3
number of a-scans in b-scan = 512
xmax mcm = 3072.0
number of b-scans = 1
ymax mcm = 0.0
beam radius mcm = 10.0
number of scatterers in b-scan = 300000
"""


def write(tmp_path, text):
    path = tmp_path / "Configuration.ini"
    path.write_text(text, encoding="utf-8")
    return path


def test_defaults_are_the_task_scanner():
    config = ScannerConfig()
    assert dataclasses.asdict(config) == {
        "depth_pixels": 256, "pixel_size_um": 6.0, "wavelength_um": 1.3, "a_scans": 512,
        "xmax_um": 3072.0, "beam_radius_um": 10.0, "max_scatterers": 300_000,
    }
    assert config == DEFAULT_CONFIG
    assert config.lateral_pitch_um == 6.0
    assert config.depth_range_um == 1536.0
    assert config.shape == (256, 512)


def test_official_ini_gives_the_defaults(tmp_path):
    config = ScannerConfig.from_ini(write(tmp_path, OFFICIAL_INI))
    assert config == DEFAULT_CONFIG
    assert isinstance(config.depth_pixels, int) and isinstance(config.max_scatterers, int)


def test_mixed_case_keys_override_values(tmp_path):
    config = ScannerConfig.from_ini(write(tmp_path, """\
[Parameters]
A-Scan Pixel Numbers = 128
Vertical Pixel Size MCM = 5.5
CENTRAL WAVELENGTH MCM = 0.85
Number of A-scans in B-scan = 1024
XMax mcm = 2048
Beam Radius mcm = 7.5
number of Scatterers in B-Scan = 3e5
Number Of B-Scans = 1
"""))
    assert config == ScannerConfig(depth_pixels=128, pixel_size_um=5.5, wavelength_um=0.85,
                                   a_scans=1024, xmax_um=2048.0, beam_radius_um=7.5,
                                   max_scatterers=300_000)
    assert type(config.max_scatterers) is int and config.lateral_pitch_um == 2.0


def test_keys_left_out_keep_their_defaults(tmp_path):
    config = ScannerConfig.from_ini(write(tmp_path, "[Parameters]\nbeam radius mcm = 12\n"))
    assert config == dataclasses.replace(DEFAULT_CONFIG, beam_radius_um=12.0)


def test_missing_file_names_the_file(tmp_path):
    path = tmp_path / "absent.ini"
    with pytest.raises(ConfigError) as caught:
        ScannerConfig.from_ini(path)
    assert str(caught.value) == f"{path}: no such file"


def test_missing_parameters_section_names_file_and_section(tmp_path):
    path = write(tmp_path, "[Settings]\nbeam radius mcm = 10\n")
    with pytest.raises(ConfigError) as caught:
        ScannerConfig.from_ini(path)
    assert str(caught.value) == f"{path}: no [Parameters] section"


def test_text_without_section_header_is_not_an_ini(tmp_path):
    path = write(tmp_path, "beam radius mcm = 10\n")
    with pytest.raises(ConfigError, match="not a valid INI file") as caught:
        ScannerConfig.from_ini(path)
    assert str(caught.value).startswith(f"{path}: ")


@pytest.mark.parametrize("key, value", [
    ("beam radius mcm", "ten"),
    ("a-scan pixel numbers", "256px"),
    ("Number of Scatterers in B-scan", "lots"),
])
def test_non_number_value_names_file_key_and_value(tmp_path, key, value):
    path = write(tmp_path, f"[Parameters]\n{key} = {value}\n")
    with pytest.raises(ConfigError) as caught:
        ScannerConfig.from_ini(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: ")
    assert key.lower() in message and repr(value) in message and "not a number" in message


def test_fractional_count_is_refused_naming_the_key(tmp_path):
    path = write(tmp_path, "[Parameters]\nnumber of a-scans in b-scan = 511.5\n")
    with pytest.raises(ConfigError) as caught:
        ScannerConfig.from_ini(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: ")
    assert "number of a-scans in b-scan" in message and "'511.5' is not a whole number" in message


@pytest.mark.parametrize("key, value", [("number of b-scans", "2"), ("Number of B-scans", "two"),
                                        ("ymax mcm", "100.0")])
def test_volume_settings_are_refused_naming_file_and_key(tmp_path, key, value):
    path = write(tmp_path, f"[Parameters]\n{key} = {value}\n")
    with pytest.raises(ConfigError) as caught:
        ScannerConfig.from_ini(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: ")
    assert key.lower() in message and repr(value) in message and "single" in message


@pytest.mark.parametrize("key, value, field", [
    ("beam radius mcm", "-1", "beam_radius_um"),
    ("a-scan pixel numbers", "255", "depth_pixels"),
    ("central wavelength mcm", "nan", "wavelength_um"),
    ("number of scatterers in b-scan", "0", "max_scatterers"),
])
def test_invalid_values_name_the_file_and_key(tmp_path, key, value, field):
    path = write(tmp_path, f"[Parameters]\n{key} = {value}\n")
    with pytest.raises(ConfigError) as caught:
        ScannerConfig.from_ini(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: ") and key in message and field in message, message


@pytest.mark.parametrize("kwargs", [{"depth_pixels": 0}, {"beam_radius_um": float("inf")},
                                    {"depth_pixels": 255}, {"xmax_um": -3072.0}])
def test_constructor_refuses_invalid_geometry(kwargs):
    with pytest.raises(ConfigError, match=next(iter(kwargs))):
        ScannerConfig(**kwargs)


def test_directory_and_binary_files_are_config_errors(tmp_path):
    with pytest.raises(ConfigError, match="is a directory"):
        ScannerConfig.from_ini(tmp_path)
    path = tmp_path / "binary.ini"
    path.write_bytes(b"[Parameters]\nbeam radius mcm = \xff\xfe\n")
    with pytest.raises(ConfigError, match="not a text file") as caught:
        ScannerConfig.from_ini(path)
    assert str(caught.value).startswith(f"{path}: ")
