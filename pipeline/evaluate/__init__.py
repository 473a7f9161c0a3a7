"""Evaluation: how good are a run's holes, causes and fills, against a truth.

- :mod:`.truth`: a run scored against a truth raster of causes (IoU, cause accuracy;
  ``score_holes``, ``score_run``: ``holefill evaluate OUT --truth``);
- :mod:`.causes`: a real survey's hole causes scored against evidence the rules do not
  see (``bench/bench_causes_real.py``);
- :mod:`.fill`: the fill benchmark (``holefill evaluate --fill``).

Nothing is imported here: import from the modules.
"""
