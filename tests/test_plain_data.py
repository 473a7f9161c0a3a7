"""Kept results are data only: what a run reads back from its output folder never runs code."""

from __future__ import annotations

import json
import os
import pickle
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from pipeline.grid import PixelWindow
from pipeline.io.intermediate import FORMAT_VERSION, load_object, save_object
from pipeline.stages.bin_tiles import TileResult
from pipeline.survey.ground_level import GroundLevel


@dataclass(frozen=True)
class Later:
    """A result as another stage may grow it: new fields of arrays, scalars, strings and tuples."""

    sums: np.ndarray
    records: np.ndarray
    name: str = ""
    pairs: tuple[tuple[int, float], ...] = ()
    by_key: dict = field(default_factory=dict)


def test_dataclasses_of_arrays_scalars_and_containers_round_trip(tmp_path):
    records = np.zeros(3, dtype=[("hole_id", "<i8"), ("cause", "<U16"), ("ok", "?")])
    records["cause"] = ["water", "occlusion", ""]
    value = {
        "tile": TileResult(3, "/a/b.laz", "/w/t", PixelWindow(1, 2, 3, 4), 10, 9, 1, 0.5, ground=GroundLevel()),
        "later": [None, np.float32(2.5), np.int64(7), b"\x00wkb", {1, 2}, frozenset({"a"}), Path("/x")],
        (500_000, 4_999_750): np.arange(6, dtype=np.uint16).reshape(2, 3),
    }
    save_object(tmp_path / "r.npz", value)
    back = load_object(tmp_path / "r.npz")
    assert back["tile"] == value["tile"]
    assert back["later"][:3] == [None, 2.5, 7] and type(back["later"][1]) is np.float32
    assert back["later"][3:] == value["later"][3:]
    np.testing.assert_array_equal(back[(500_000, 4_999_750)], value[(500_000, 4_999_750)])


def test_new_fields_of_plain_kinds_need_no_code(tmp_path, monkeypatch):
    monkeypatch.setattr("pipeline.io.plain_data.TRUSTED_PACKAGE", __name__.split(".")[0])
    records = np.zeros(2, dtype=[("line", "<i8"), ("n", "<f8")])
    value = Later(np.ones(4), records, "x", ((1, 2.0),), {("a", 1): 3})
    save_object(tmp_path / "r.npz", value)
    back = load_object(tmp_path / "r.npz")
    assert back.name == "x" and back.pairs == ((1, 2.0),) and back.by_key == {("a", 1): 3}
    np.testing.assert_array_equal(back.records, records)


class Payload:
    def __reduce__(self):
        return (os.system, (f"touch {os.environ['PLANTED_MARKER']}",))


def planted_pickle(path: Path, marker: Path) -> None:
    os.environ["PLANTED_MARKER"] = str(marker)
    path.write_bytes(pickle.dumps((FORMAT_VERSION, Payload())))


def planted_tree(path: Path, tree: dict) -> None:
    np.savez(path, tree=np.frombuffer(json.dumps({"version": FORMAT_VERSION, "value": tree}).encode(), np.uint8))


@pytest.mark.parametrize(
    "tree",
    [
        {"$c": "subprocess:Popen", "v": {}},  # not one of holefill's classes
        {"$e": "os:system", "v": "touch x"},
        {"$c": "pipeline.grid:PixelWindow", "v": {"row_off": 1}},  # fields missing
        {"$c": "pipeline.grid:PixelWindow", "v": {"row_off": "1", "col_off": 0, "height": 1, "width": 1}},
        {"$c": "pipeline.staging:Staging.create", "v": {}},  # not a dataclass
        {"$c": "pipeline.no_such_module:Thing", "v": {}},  # a class this version does not have
        {"$c": "pipeline.grid:NoSuchClass", "v": {}},
        {"$x": 1},
    ],
)
def test_unexpected_content_is_refused(tmp_path, tree):
    planted_tree(tmp_path / "r.npz", tree)
    with pytest.raises(ValueError):
        load_object(tmp_path / "r.npz")


def test_a_class_kept_under_its_module_before_a_move_reads_back(tmp_path):
    """An older run's kept results (``--incremental``) name classes where they were then."""
    fields = {"points": 5, "at_zero": 0}
    planted_tree(tmp_path / "r.npz", {"$c": "pipeline.ground_level:GroundLevel", "v": fields})
    assert load_object(tmp_path / "r.npz") == GroundLevel(5, 0)


def test_a_planted_pickle_is_not_run(tmp_path):
    marker = tmp_path / "ran"
    planted_pickle(tmp_path / "r.npz", marker)
    with pytest.raises(ValueError):
        load_object(tmp_path / "r.npz")
    assert not marker.exists()


def test_object_arrays_are_not_kept(tmp_path):
    with pytest.raises(TypeError):
        save_object(tmp_path / "r.npz", np.array([object()]))
    assert not list(tmp_path.iterdir())


def test_a_write_cut_short_leaves_nothing_a_result_glob_finds(tmp_path, monkeypatch):
    """A task killed between writing its result and renaming it left ``<name>.tmp.npz``, which
    ``rasterize-*.npz`` counted as a kept result (a resume test saw 6 kept and 5 resumed)."""
    target = tmp_path / "rasterize-tile-part003.npz"
    save_object(target, TileResult(0, "a.laz", "out", PixelWindow(0, 0, 1, 1), 1, 1, 0, 0.1))
    assert [p.name for p in tmp_path.iterdir()] == [target.name]

    def killed(source, destination):
        raise KeyboardInterrupt  # the process dies before the rename

    monkeypatch.setattr(os, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        save_object(tmp_path / "rasterize-tile-part004.npz", 1)
    assert [p.name for p in tmp_path.glob("rasterize-*.npz")] == [target.name]
    assert load_object(target).tile_index == 0
