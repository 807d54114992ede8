"""Site configuration (docs/configuration.md): TOML file, checked key by key, overridden by flags."""

from __future__ import annotations

import pytest

from uwbcl import config
from uwbcl.cli import main

SITE = """
[processing]
algorithm = "bp"
backend = "numpy"
jobs = 3

[site]
web_depth_m = 0.85
prior_window_m = [0.3, 0.2, 0.4]
heights_m = [0.2, 0.6]

[association]
min_confident_targets = 3
range_sigma_m = 0.004
max_bridge_cycles = 2

[detection]
min_snr_db = 14.0

[output]
plots = true
hdf5 = false
"""


def write(tmp_path, text):
    path = tmp_path / "site.toml"
    path.write_text(text)
    return path


def test_every_section_reaches_the_settings_it_names(tmp_path):
    cfg = config.load_config(write(tmp_path, SITE))
    s = cfg.processing_settings()
    assert (s.algorithm, s.backend) == ("bp", "numpy")
    assert s.association.prior_advance_m == (0.85, 0.0, 0.0)
    assert s.association.prior_window_m == (0.3, 0.2, 0.4)
    assert s.association.min_confident_targets == 3 and s.association.range_sigma_m == 0.004
    assert s.detection.min_snr_db == 14.0
    opts = cfg.batch_options()
    assert opts.jobs == 3 and opts.heights_m == (0.2, 0.6) and opts.max_bridge_cycles == 2
    assert opts.outputs.plots and not opts.outputs.hdf5 and opts.outputs.targets


def test_command_line_flags_override_the_file(tmp_path):
    cfg = config.override(config.load_config(write(tmp_path, SITE)), web_depth_m=0.95, jobs=None,
                          backend=None, plots=None, hdf5=True)
    s = cfg.processing_settings()
    assert s.association.prior_advance_m[0] == 0.95
    assert cfg.jobs == 3 and s.backend == "numpy"  # flags left unset keep the file's values
    assert cfg.output.hdf5 and cfg.output.plots


def test_without_a_file_the_defaults_apply():
    s = config.SiteConfig().processing_settings()
    assert s.association.prior_advance_m is None and s.algorithm == "nlcs"


@pytest.mark.parametrize(("text", "key"), [
    ("[site]\nweb_depth = 0.9\n", "site.web_depth"),
    ("[sites]\nweb_depth_m = 0.9\n", "sites"),
    ("[site]\nweb_depth_m = '0.9'\n", "site.web_depth_m"),
    ("[site]\nweb_depth_m = -0.9\n", "site.web_depth_m"),
    ("[site]\nheights_m = [0.2]\n", "site.heights_m"),
    ("[association]\ntolerance_m = [0.05, 0.1]\n", "association.tolerance_m"),
    ("[processing]\nbackend = 'cuda'\n", "processing.backend"),
    ("[detection]\ncross_height_x_tol_m = 0.0\n", "detection.cross_height_x_tol_m"),
    ("[detection]\ncross_height_rc_tol_m = nan\n", "detection.cross_height_rc_tol_m"),
    ("[detection]\ncross_height_wall_tol_m = -0.1\n", "detection.cross_height_wall_tol_m"),
    ("[site]\nweb_depth_m = 1e308\n", "site.web_depth_m"),  # finite, but no length of a gate road
    ("[site]\nheights_m = [0.2, 1e300]\n", "site.heights_m"),
    ("[site]\nheight_tolerance_m = 1e9\n", "site.height_tolerance_m"),
    ("[association]\ntolerance_m = [1e300, 0.1, 0.1]\n", "association.tolerance_m"),
    ("[association]\nmax_bridge_cycles = 9223372036854775807\n", "association.max_bridge_cycles"),
    # finite and > 0, yet they broke the maths (an independent tester: tracebacks, or every pass failed)
    ("[association]\nrange_sigma_m = 1e-300\n", "association.range_sigma_m"),
    ("[detection]\nseparation_m = 1e-300\n", "detection.separation_m"),
    ("[detection]\nseparation_m = 1000.0\n", "detection.separation_m"),
    ("[detection]\nmin_snr_db = 1e308\n", "detection.min_snr_db"),
    ("[detection]\ncfar_db = 1e308\n", "detection.cfar_db"),
    ("[site\n", ""),  # the file itself: no key
    ("web_depth_m = 0.9\n", "web_depth_m"),  # a key outside any table
])
def test_a_mistake_names_the_file_and_the_key(tmp_path, text, key):
    path = write(tmp_path, text)
    with pytest.raises(config.ConfigError) as info:
        config.load_config(path).processing_settings()
    assert info.value.key == key
    assert str(path) in str(info.value)


def test_cli_refuses_a_bad_config_before_touching_anything(tmp_path, capsys):
    path = write(tmp_path, "[site]\nweb_depth = 0.9\n")
    out = tmp_path / "out"
    assert main(["process", str(tmp_path), "--out", str(out), "--config", str(path)]) == 2
    assert "site.web_depth" in capsys.readouterr().err
    assert not out.exists()


def test_one_site_file_serves_process_and_acquire(tmp_path):
    """`uwbcl acquire` reads the [acquire] table of the same file; `uwbcl process` leaves it to it."""
    path = write(tmp_path, SITE + '\n[acquire]\nhost = "127.0.0.1"\nport = 5020\n')
    assert config.load_config(path) == config.load_config(write(tmp_path, SITE))


def test_the_range_table_of_configuration_md_lists_every_range_the_code_checks():
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "configuration.md").read_text(encoding="utf-8")
    table = text[text.index("| key | must be |"):]
    table = table[:table.index("\n\n")]
    documented = set(re.findall(r"`([a-z_]+\.[a-z_0-9*]+)`", table))
    checked = {k for k in config._RANGES if not k.startswith("limits.")} - {"association.prior_window_m"}
    checked |= {"site.web_depth_m", "site.height_tolerance_m", "processing.jobs", "site.prior_creep_m",
                "site.prior_vertical_m", "site.prior_window_m", "site.heights_m", "association.max_bound_m",
                "association.max_backward_m", "association.min_margin", "association.max_bridge_cycles",
                "radar.range_delay_s", "limits.*"}  # checked in config.validate
    assert checked - documented == set()


@pytest.mark.parametrize("value, ok", [(1e-6, True), (-1e-6, True), (1.0000001e-6, False)])
def test_the_range_delay_is_accepted_within_one_microsecond_inclusive(tmp_path, value, ok):
    site = tmp_path / "site.toml"
    site.write_text(f"[radar]\nrange_delay_s = {value!r}\n")
    if ok:
        assert config.load_config(site).range_delay_s == value
    else:
        with pytest.raises(config.ConfigError, match="radar.range_delay_s"):
            config.load_config(site)


def test_a_prior_window_needs_a_web_depth_from_the_file_or_the_flags(tmp_path, capsys):
    """The window of no prior is a usage error, judged on the file and the flags together (indepZe 5)."""
    path = write(tmp_path, "[site]\nprior_window_m = [0.4, 0.3, 0.5]\n")
    site = config.load_config(path)
    with pytest.raises(config.ConfigError) as info:
        config.override(site)
    assert info.value.key == "site.prior_window_m"
    assert config.override(site, web_depth_m=0.9).processing_settings().association.prior_window_m == \
        (0.4, 0.3, 0.5)
    assert main(["process", str(tmp_path), "--out", str(tmp_path / "out"), "--prior-window", "0.4", "0.3",
                 "0.5"]) == 2
    assert "site.prior_window_m: is the window of the web-depth prior" in capsys.readouterr().err
