"""The dataset contract: layout, loading with pipe's conventions, validation and preprocessing."""

from pipe.data.dataset import Dataset, Part, StaticCurve, Trial, load_dataset, load_part, load_trial
from pipe.data.spec import DatasetSpec, load_spec

__all__ = [
    "Dataset",
    "DatasetSpec",
    "Part",
    "StaticCurve",
    "Trial",
    "load_dataset",
    "load_part",
    "load_spec",
    "load_trial",
]
