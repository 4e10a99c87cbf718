"""pipe.model.novelty: a part's distance to its nearest training part over the training parts' coverage radius."""

from __future__ import annotations

import json

import pytest
import torch

from pipe.model.novelty import Novelty, coverage_radius, nearest_other_distances, novelty

# training parts on a line at 0, 1 and 3: nearest-other distances 1, 1 and 2, so the coverage radius is 2
REFERENCE = torch.tensor([[0.0, 0.0], [1.0, 0.0], [3.0, 0.0]])
NAMES = ("a", "b", "c")


def test_nearest_other_distances_by_hand():
    assert nearest_other_distances(REFERENCE).tolist() == pytest.approx([1.0, 1.0, 2.0])
    assert nearest_other_distances(torch.tensor([[0.0, 0.0], [3.0, 4.0]])).dtype == torch.float64


def test_the_coverage_radius_is_the_largest_nearest_other_distance():
    assert coverage_radius(REFERENCE) == pytest.approx(2.0)
    assert coverage_radius(torch.tensor([[0.0, 0.0], [3.0, 4.0]])) == pytest.approx(5.0)


@pytest.mark.parametrize("reference", [REFERENCE[:1], torch.zeros(3, 2)])
def test_one_part_or_parts_at_one_point_span_no_radius(reference):
    assert coverage_radius(reference) is None
    assert novelty(torch.ones(1, 2), reference, NAMES[:len(reference)]) is None


def test_novelty_by_hand():
    codes = torch.tensor([[0.4, 0.0], [2.2, 0.0], [6.0, 0.0], [3.0, 2.5]])
    found = novelty(codes, REFERENCE, NAMES)
    assert [n.nearest for n in found] == ["a", "c", "c", "c"]
    assert [n.distance for n in found] == pytest.approx([0.4, 0.8, 3.0, 2.5])
    assert [n.ratio for n in found] == pytest.approx([0.2, 0.4, 1.5, 1.25])
    assert [n.extrapolates for n in found] == [False, False, True, True]


def test_a_training_part_itself_is_no_extrapolation_and_the_radius_is_the_boundary():
    found = novelty(REFERENCE, REFERENCE, NAMES)
    assert [n.nearest for n in found] == list(NAMES) and all(n.ratio == 0.0 for n in found)
    assert not Novelty("c", 2.0, 1.0).extrapolates and Novelty("c", 2.0, 1.0 + 1e-9).extrapolates


def test_the_report_gives_each_test_parts_novelty(trained_run):
    """results.json and results.md name dsub26's nearest training part and its ratio, by brute force over the
    run's own codes of its two training parts."""
    latents, index = trained_run.latents.double(), trained_run.index
    distances = {name: float((latents[index["dsub26"]] - latents[index[name]]).norm()) for name in ("dsub9", "dsub15")}
    radius = float((latents[index["dsub9"]] - latents[index["dsub15"]]).norm())
    nearest = min(distances, key=distances.get)
    doc = json.loads((trained_run.run_dir / "report" / "results.json").read_text())
    assert doc["novelty"]["dsub26"]["nearest_training_part"] == nearest
    assert doc["novelty"]["dsub26"]["ratio"] == pytest.approx(distances[nearest] / radius, rel=1e-5)
    table = (trained_run.run_dir / "report" / "results.md").read_text()
    assert f"| dsub26 | {nearest} | {distances[nearest] / radius:.2f} |" in table
