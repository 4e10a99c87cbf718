"""Bringing recordings in: readers of robot and sensor logs (`readers`, `streams`), the cut of each
recording to one insertion (`insertion`) and `pipe data import` (`dataset_import`)."""

from pipe.importing import readers, streams  # noqa: F401  (both fill readers.READERS)
