"""The embedded default dataset: the paper's 27 parts built from standard dimensions, and a simulator of
their robot-guided insertion with ground truth (noise-free force, true static force-depth curve)."""

from pipe.synthetic.catalogue import CATALOGUE, PART_NAMES
from pipe.synthetic.generate import generate_dataset, generated_part_names

__all__ = ["CATALOGUE", "PART_NAMES", "generate_dataset", "generated_part_names"]
