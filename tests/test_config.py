from __future__ import annotations

import dataclasses
import re
import tomllib
from pathlib import Path

import pytest

from pipeline.config import SECTIONS, Config, load_config, to_dict
from pipeline.errors import ConfigError

from .conftest import REPO

DEFAULT_TOML = REPO / "configs" / "default.toml"


def test_default_toml_matches_the_built_in_defaults():
    with DEFAULT_TOML.open("rb") as fh:
        assert tomllib.load(fh) == to_dict(Config())
    assert load_config(DEFAULT_TOML) == Config()


def test_every_key_is_documented_in_default_toml():
    text = DEFAULT_TOML.read_text()
    for section, cls in SECTIONS.items():
        for f in dataclasses.fields(cls):
            assert f.metadata.get("doc"), f"{section}.{f.name} has no description in pipeline/config.py"
            # the line before each key in configs/default.toml is a comment
            match = re.search(rf"#[^\n]*\n{f.name} = ", text)
            assert match, f"configs/default.toml: document [{section}] {f.name} with a comment line above it"


def test_overrides_are_typed_and_validated():
    config = load_config(overrides=["grid.resolution_m=0.5", "filter.keep_classes=[2]", "survey.crs=EPSG:28992"])
    assert config.grid.resolution_m == 0.5
    assert config.filter.keep_classes == [2]
    assert config.survey.crs == "EPSG:28992"
    assert load_config().grid.resolution_m == "auto" and load_config().holes.min_area_m2 == "auto"
    assert load_config(overrides=["grid.resolution_m=auto"]).grid.resolution_m == "auto"
    # a cell size that is no multiple of the pixel is rounded when the survey is planned, not refused
    assert load_config(overrides=["grid.resolution_m=4", "grid.cell_size_m=250"]).grid.cell_size_m == 250.0


@pytest.mark.parametrize(
    "override, words",
    [
        ("grid.resolution=1", ["unknown key 'grid.resolution'", "resolution_m"]),
        ("gird.resolution_m=1", ["unknown section 'gird'", "grid"]),
        ("grid.resolution_m=-2", ["grid.resolution_m", "> 0"]),
        ("output.compress=jpeg", ["output.compress", "'deflate'", "'zstd'"]),
        ("filter.drop_classes=7", ["filter.drop_classes", "list of int"]),
        ("filter.drop_classes=[7, 300]", ["between 0 and 255"]),
        ("grid.resolution_m=fine", ["grid.resolution_m", "a number or 'auto'"]),
        ("holes.min_area_m2=-1", ["holes.min_area_m2", ">= 0"]),
        ("grid.align=corner", ["grid.align", "'edge'", "'center'"]),
        ("survey.on_error=ignore", ["'fail'", "'skip'"]),
        ("dask.workers=1.5", ["dask.workers", "int"]),
        ("noequals", ["section.key=value"]),
    ],
)
def test_bad_overrides_name_the_key_and_allowed_values(override, words):
    with pytest.raises(ConfigError) as info:
        load_config(overrides=[override])
    message = str(info.value)
    assert f"--set {override}" in message
    for word in words:
        assert word in message


def test_bad_file_names_the_file_and_key(tmp_path):
    path = tmp_path / "my.toml"
    path.write_text("[grid]\nresolution_m = 1.0\ncel_size_m = 100\n")
    with pytest.raises(ConfigError, match=r"my\.toml: unknown key 'grid\.cel_size_m'.*cell_size_m"):
        load_config(path)
    path.write_text("[grid\n")
    with pytest.raises(ConfigError, match=r"my\.toml: not valid TOML"):
        load_config(path)
    path.write_text("[output]\nblocksize = 300\n")
    with pytest.raises(ConfigError, match=r"my\.toml: output\.blocksize = 300 is invalid; expected one of 128, 256"):
        load_config(path)
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "missing.toml")


def test_precedence_file_then_set(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("[grid]\nresolution_m = 2.0\ncell_size_m = 200.0\n")
    config = load_config(path, ["grid.resolution_m=0.5"])
    assert config.grid.resolution_m == 0.5 and config.grid.cell_size_m == 200.0


def test_to_toml_round_trips(tmp_path):
    config = load_config(overrides=["grid.resolution_m=0.25", "filter.keep_classes=[2, 9]"])
    path = tmp_path / "shown.toml"
    path.write_text(config.to_toml())
    assert load_config(path) == config


def test_flightplan_docs_and_config_show_agree_on_defaults():
    """docs/flightplans.md's table, `holefill config --show` and configs/default.toml say the same defaults."""
    from click.testing import CliRunner

    from pipeline.cli import main
    from pipeline.config import FlightPlanConfig

    docs = (DEFAULT_TOML.parents[1] / "docs" / "flightplans.md").read_text()
    shown = CliRunner().invoke(main, ["config", "--show"]).output
    for f in dataclasses.fields(FlightPlanConfig):
        row = re.search(rf"^\| `{f.name}` \| `([^`]*)` \| (.*) \|$", docs, re.MULTILINE)
        assert row, f"docs/flightplans.md: no table row for flightplan.{f.name}"
        default = getattr(Config().flightplan, f.name)
        assert tomllib.loads(f"v = {row.group(1)}")["v"] == default, f.name
        if f.name == "home":  # what an empty home means, in every place
            meaning = f.metadata["doc"].split("; ", 1)[1].rstrip(".")
            assert meaning.replace("'", "`") in row.group(2)
            assert meaning in shown and meaning.replace("'", "`").replace(" `holefill plan`", "") in " ".join(
                line.lstrip("# ") for line in DEFAULT_TOML.read_text().splitlines()
            )


def test_papers_cited_in_the_docs_exist():
    """Every seeds file the docs cite is named by its path from the repository root, and exists there."""
    cited = {
        (doc.name, path)
        for doc in (REPO / "docs").glob("*.md")
        for path in re.findall(r"`([^`\s]*seeds/[^`\s]+)`", doc.read_text())
    }
    assert cited, "no paper is cited from ../shared/seeds"
    assert all(path.startswith("../shared/seeds/") for _, path in cited), cited
    if not (REPO.parent / "shared" / "seeds").is_dir():
        pytest.skip("../shared/seeds is not beside this checkout")
    missing = sorted((doc, path) for doc, path in cited if not (REPO / path).is_file())
    assert not missing, missing


def test_a_relative_file_in_a_configuration_file_is_relative_to_its_folder(tmp_path, monkeypatch):
    """A configuration kept beside its water polygons works from any working directory."""
    folder = tmp_path / "project"
    folder.mkdir()
    (folder / "run.toml").write_text('[holes]\nwater = "lakes.gpkg"\n')
    monkeypatch.chdir(tmp_path)
    config = load_config(folder / "run.toml")
    assert Path(config.holes.water) == folder / "lakes.gpkg"
    # from --set, relative to the working directory, as a command line's paths are
    assert load_config(overrides=["holes.water=lakes.gpkg"]).holes.water == "lakes.gpkg"
    (folder / "abs.toml").write_text(f'[holes]\nwater = "{tmp_path / "elsewhere.gpkg"}"\n')
    assert Path(load_config(folder / "abs.toml").holes.water) == tmp_path / "elsewhere.gpkg"


@pytest.mark.parametrize(
    "value",
    ["/vsicurl/https://example.org/lakes.gpkg", "https://example.org/pipeline.json", "/vsis3/bucket/lakes.gpkg"],
)
def test_a_network_path_in_a_configuration_needs_an_opt_in(tmp_path, value):
    (tmp_path / "run.toml").write_text(f'[holes]\nwater = "{value}"\n')
    with pytest.raises(ConfigError, match=r"run.toml: holes.water = .* is a network path; set read.allow_network"):
        load_config(tmp_path / "run.toml")
    allowed = load_config(tmp_path / "run.toml", overrides=["read.allow_network=true"])
    assert allowed.holes.water == value  # left as written, never joined to the file's folder


@pytest.mark.parametrize(
    ("overrides", "ground", "plans"),
    [
        ([], True, True),
        (["flightplan.enabled=false"], True, False),  # the same tiles: an incremental run reuses them
        (["holes.enabled=false"], False, False),  # the DSM alone: no sums
    ],
)
def test_stage_1_keeps_the_ground_s_sums_wherever_holes_are_sought(overrides, ground, plans):
    """The take-off's ground sums follow ``holes.enabled`` alone: flight plans turned on or off keep
    every tile's stage-1 result (its fingerprint holds the flag), a DSM-only run sums nothing."""
    from pipeline.parameters import read_params

    config = load_config(overrides=overrides)
    assert read_params(config, vertical_unit_m=1.0).ground is ground
    assert config.plans_flights is plans
