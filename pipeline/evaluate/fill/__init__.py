"""The fill benchmark: cut artificial holes into real surveys, fill them, score the fills.

For each survey (and each surface model, DSM or DTM) the benchmark

1. runs the pipeline on the full survey without filling: the *reference* raster;
2. places seeded artificial holes (discs, rotated rectangles, irregular blobs,
   2 m to 50 m across) where the reference is measured over the hole and a margin
   around it, apart from each other (:func:`place_holes`);
3. writes a copy of each input file without the points that fall in those pixels
   (:func:`cut_points`): the removed pixels are exactly the hole pixels;
4. runs the pipeline on the cut copy once per fill method (``--set``-style
   overrides of ``[fill]``) and scores each filled raster on the removed pixels
   against the reference (:func:`fill_errors`);
5. fills the same holes of the cut survey's unfilled raster with the usual
   alternatives (:data:`ALTERNATIVES`: GDAL fillnodata, a linear TIN, startinpy's
   natural-neighbour and Laplace interpolation, GRASS ``r.fillnulls``) and scores
   them the same way.

The array functions (:func:`hole_shape`, :func:`place_holes`, :func:`fill_errors`,
the alternatives) take and return arrays; :func:`evaluate_fill` is the tool that
reads and writes files and runs the pipeline. Rows and columns are pixels, x/y are
world coordinates; heights are in the survey's z unit.

Modules: :mod:`.placement` (hole shapes and placement), :mod:`.cutting` (cutting the
points), :mod:`.alternatives`, :mod:`.metrics` (:class:`ErrorStats`), :mod:`.results`
(per method, survey and benchmark), :mod:`.benchmark` (the driver) and
:mod:`.formatting` (``fill_eval.json`` and the text table).
"""

# shutil is re-exported for the tests, which patch ``shutil.which`` through this module
import shutil as shutil

from .alternatives import (
    ALTERNATIVES,
    AlternativeUnavailable,
    fill_gdal,
    fill_grass,
    fill_laplace,
    fill_nni,
    fill_tin_linear,
    grass_tmp_option,
    parse_grass_version,
)
from .benchmark import MODELS, PIPELINE_RUNS, BenchmarkPlan, evaluate_fill, survey_name
from .cutting import align, cut_points, pixel_indices
from .formatting import format_table, write_json
from .metrics import ErrorStats, fill_errors
from .placement import RESOLUTIONS_M, SHAPES, CutHole, choose_resolution, hole_shape, place_holes
from .results import FillBenchmark, MethodResult, SurveyResult, summarize

__all__ = [
    "ALTERNATIVES",
    "BenchmarkPlan",
    "MODELS",
    "PIPELINE_RUNS",
    "RESOLUTIONS_M",
    "SHAPES",
    "AlternativeUnavailable",
    "CutHole",
    "ErrorStats",
    "FillBenchmark",
    "MethodResult",
    "SurveyResult",
    "align",
    "choose_resolution",
    "cut_points",
    "evaluate_fill",
    "fill_errors",
    "fill_gdal",
    "fill_grass",
    "fill_laplace",
    "fill_nni",
    "fill_tin_linear",
    "format_table",
    "grass_tmp_option",
    "hole_shape",
    "pixel_indices",
    "parse_grass_version",
    "place_holes",
    "summarize",
    "survey_name",
    "write_json",
]
