"""Trials aligned on their final depth (pipe.data.alignment, `data.align_final_depth`)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import smoke_config

from pipe.data.alignment import align_final_depth, final_depth_shifts
from pipe.data.dataset import StaticCurve
from pipe.data.prepared import PartData
from pipe.data.preprocess import Profile


def test_shifts_move_every_deepest_point_to_their_median():
    assert final_depth_shifts([10.0, 11.0, 12.5]) == pytest.approx([1.0, 0.0, -1.5])
    assert final_depth_shifts([4.0, 6.0]) == pytest.approx([1.0, -1.0])      # an even count: the mean of the two
    assert final_depth_shifts([7.0]) == [0.0]


def _profile(depths: list[float]) -> Profile:
    depth = np.array(depths)
    return Profile(np.arange(len(depth)) * 0.01, depth, depth * 2.0, None)


def test_a_parts_trials_are_shifted_whole_their_force_and_static_curves_kept_in_step():
    profiles = [_profile([0.0, 3.0, 10.0, 10.0]), _profile([0.0, 4.0, 11.0, 11.0]), _profile([0.0, 2.0, 12.5])]
    statics = [StaticCurve(np.array([1.0, 9.0]), np.array([0.5, 3.0])), None, StaticCurve(np.array([2.0]),
                                                                                          np.array([1.0]))]
    part = PartData("p", cloud=None, profiles=profiles, static_curves=statics)
    aligned = align_final_depth(part)
    assert [p.depth.max() for p in aligned.profiles] == pytest.approx([11.0, 11.0, 11.0])
    assert aligned.profiles[0].depth.tolist() == pytest.approx([1.0, 4.0, 11.0, 11.0])     # shifted whole
    assert aligned.profiles[2].depth.tolist() == pytest.approx([-1.5, 0.5, 11.0])
    for before, after in zip(profiles, aligned.profiles):      # nothing but the depth changes
        assert after.force is before.force and after.time is before.time
    assert aligned.static_curves[0].depth.tolist() == pytest.approx([2.0, 10.0])         # the trial's own shift
    assert aligned.static_curves[1] is None and aligned.static_curves[2].depth.tolist() == pytest.approx([0.5])
    assert part.profiles[0].depth.tolist() == [0.0, 3.0, 10.0, 10.0]                      # the input is not changed
    single = PartData("q", cloud=None, profiles=[profiles[1]], static_curves=[None])
    assert align_final_depth(single).profiles[0].depth.tolist() == profiles[1].depth.tolist()
    empty = PartData("r", cloud=None, profiles=[], static_curves=[])
    assert align_final_depth(empty) is empty


def _entry_depths(part: PartData) -> np.ndarray:
    """Per trial, the TCP depth at which the generator's true static force first passes 0.1 N: where the plug
    meets the receptacle's lead-in, a fixed place of the part."""
    return np.array([curve.depth[np.argmax(curve.force > 0.1)] for curve in part.static_curves])


def test_alignment_puts_a_parts_features_at_one_depth_whatever_each_trials_gap(tiny_data, tmp_path):
    """The generator starts every trial 1 to 2 mm short of contact (its gap) and ends it 0.1 to 0.3 mm past the
    stop (docs/synthetic.md, "Trials"): aligned on their final depth, the trials' contact entries come within
    the overtravel's spread instead of the gap's."""
    from pipe.pipeline import load_domain

    plain = load_domain(smoke_config(tiny_data, tmp_path))
    aligned = load_domain(smoke_config(tiny_data, tmp_path, "data.align_final_depth=true"))
    for split in plain.splits:
        for before, after in zip(plain.splits[split], aligned.splits[split]):
            spread_before, spread_after = np.ptp(_entry_depths(before)), np.ptp(_entry_depths(after))
            assert spread_before > 0.4 and spread_after < 0.25, (before.name, spread_before, spread_after)
            assert len({round(float(p.depth.max()), 9) for p in after.profiles}) == 1
            for p, q in zip(before.profiles, after.profiles):
                assert np.array_equal(p.force, q.force)


def test_a_folder_is_continued_and_evaluated_only_with_the_alignment_it_was_trained_with(tiny_data, tmp_path):
    from pipe.errors import PipeError
    from pipe.pipeline import run_domain

    trained = tmp_path / "trained"
    common = ("mlflow.enabled=false", "evaluation.baselines=[nearest]")
    aligned = run_domain(smoke_config(tiny_data, trained, *common, "data.align_final_depth=true"))
    again = run_domain(smoke_config(tiny_data, tmp_path / "again", *common, "data.align_final_depth=true",
                                    "phase=evaluate", f"resume={trained}"))
    assert again.pipe.domain == aligned.pipe.domain
    for folder, phase in ((tmp_path / "other", "evaluate"), (trained, "all")):
        with pytest.raises(PipeError, match="was trained with data.align_final_depth=true; continue or evaluate"):
            run_domain(smoke_config(tiny_data, folder, *common, f"phase={phase}", f"resume={trained}"))
