"""The cloud's cross-section beside the encoder's code (code.sections): the descriptor against values worked
out by hand, its standardisation over the training parts, the code PIPE and every baseline read, and the
settings a trained folder must be evaluated or resumed with."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import smoke_config

from pipe.data.batches import stack_clouds
from pipe.errors import PipeError
from pipe.model.sections import (
    LENGTH_FRACTIONS,
    SECTION_SIZE,
    TIP_REACHES_MM,
    SectionCode,
    section_descriptor,
)
from pipe.model.standardiser import MIN_SPREAD
from pipe.model.uncertainty import BandSettings, latent_draws
from pipe.pipeline import build_components, build_model, load_domain, run_domain


def stepped_pin() -> torch.Tensor:
    """A part 10 mm long: a 0.3 x 0.2 mm tip face at z = -4, a 1 x 0.6 section from 0.15 mm on, and from 4 mm
    on a 2.5 x 1.5 body (half-widths in x, y)."""
    corners = [(1, 1), (1, -1), (-1, 1), (-1, -1)]
    rings = [(-4.0, 0.3, 0.2), (-3.85, 1.0, 0.6), (-2.0, 1.0, 0.6), (0.0, 2.5, 1.5), (6.0, 2.5, 1.5)]
    return torch.tensor([[sx * hx, sy * hy, z] for z, hx, hy in rings for sx, sy in corners])


def test_the_descriptor_is_the_length_and_the_half_widths_within_each_reach_worked_out_by_hand():
    values = section_descriptor(stepped_pin()[None])[0]
    assert values.shape == (SECTION_SIZE,) and SECTION_SIZE == 1 + 2 * (len(TIP_REACHES_MM) + len(LENGTH_FRACTIONS))
    assert values[0].item() == pytest.approx(math.log(10.0))
    # reaches 0.02, 0.1 (tip face only), 0.2, 0.5, 1, 2 (tip section), 5, 10 (body); then 2.5, 5, 7.5, 10 mm
    expected = [(0.3, 0.2)] * 2 + [(1.0, 0.6)] * 4 + [(2.5, 1.5)] * 2 + [(1.0, 0.6)] + [(2.5, 1.5)] * 3
    assert torch.allclose(values[1:].exp(), torch.tensor(expected, dtype=torch.float64).flatten())


def test_a_quarter_turn_about_the_axis_or_a_shift_along_it_changes_nothing():
    pin = stepped_pin()
    turned = torch.stack([-pin[:, 1], pin[:, 0], pin[:, 2] + 3.0], dim=1)
    assert torch.allclose(section_descriptor(turned[None]), section_descriptor(pin[None]))


def test_the_training_parts_are_standardised_and_a_spread_below_the_clouds_resolution_is_raised_to_it():
    base = stepped_pin()
    train = torch.stack([base * torch.tensor([s, s, 1.0]) for s in (0.8, 1.0, 1.3)])   # widths vary, length not
    code = SectionCode.fitted(train)
    codes = code(train)
    assert torch.allclose(codes[:, 1:].mean(0), torch.zeros(SECTION_SIZE - 1), atol=1e-6)
    assert torch.allclose(codes[:, 1:].std(0), torch.ones(SECTION_SIZE - 1), atol=1e-6)
    assert torch.equal(codes[:, 0], torch.zeros(3))      # the length is the same in all three
    longer = (base * torch.tensor([1.0, 1.0, 2.0]))[None]
    assert code(longer)[0, 0].item() == pytest.approx(math.log(2.0) / MIN_SPREAD, rel=1e-6)
    assert codes.dtype == torch.float32
    with pytest.raises(ValueError, match="at least 2 training parts"):
        SectionCode.fitted(train[:1])


def test_the_code_is_the_encoders_followed_by_the_sections_without_spread(tiny_data, tmp_path):
    cfg = smoke_config(tiny_data, tmp_path, "code.slices=false")
    data = load_domain(cfg)
    model = build_model(cfg, data)
    encoder_dim = model.encoder.latent_dim
    assert model.head.latent_dim == encoder_dim + SECTION_SIZE
    clouds = stack_clouds(data.splits["test"])
    mu, logvar = model.latent_distribution(clouds)
    own_mu, own_logvar = model.encoder.eval().encode(clouds)
    assert torch.equal(mu[:, :encoder_dim], own_mu) and torch.equal(logvar[:, :encoder_dim], own_logvar)
    assert torch.equal(mu[:, encoder_dim:], model.sections(clouds))
    assert torch.isneginf(logvar[:, encoder_dim:]).all()
    draws = latent_draws(mu[0], logvar[0], BandSettings())
    assert torch.equal(draws[:, encoder_dim:], mu[0, encoder_dim:].expand(len(draws), -1))   # no spread drawn
    assert torch.isfinite(draws).all()
    off = smoke_config(tiny_data, tmp_path, "code.sections=false", "code.slices=false")
    assert build_model(off, data).sections is None and build_components(off)[1].latent_dim == encoder_dim


def test_sections_need_two_training_parts(tiny_data, tmp_path):
    cfg = smoke_config(tiny_data, tmp_path, "domain.train=[dsub9]")
    with pytest.raises(PipeError, match="code.sections standardises the cross-section over the training parts, "
                                        "and domain tiny has 1"):
        build_model(cfg, load_domain(cfg))


def test_a_folder_trained_without_sections_is_evaluated_only_with_that_setting(tiny_data, tmp_path):
    trained = tmp_path / "trained"
    plain = run_domain(smoke_config(tiny_data, trained, "mlflow.enabled=false", "code.sections=false",
                                    "evaluation.baselines=[nearest]"))
    again = run_domain(smoke_config(tiny_data, tmp_path / "again", "mlflow.enabled=false", "code.sections=false",
                                    "evaluation.baselines=[nearest]", "phase=evaluate", f"resume={trained}"))
    assert again.pipe.domain == plain.pipe.domain
    with pytest.raises(PipeError, match=r"trained: was trained with code.sections=false; continue or evaluate"):
        run_domain(smoke_config(tiny_data, tmp_path / "other", "mlflow.enabled=false", "phase=evaluate",
                                f"resume={trained}"))
    (trained / "config.yaml").unlink()          # a folder without its settings: its weights tell
    with pytest.raises(PipeError, match=r"differ in sections.mean, sections.std, head.trunk.0.weight "
                                        r"\(it was trained with code.sections=false\)"):
        run_domain(smoke_config(tiny_data, tmp_path / "other", "mlflow.enabled=false", "phase=evaluate",
                                f"resume={trained}"))
    with pytest.raises(PipeError, match=r"it was trained with code.sections=false\); resume with the settings"):
        run_domain(smoke_config(tiny_data, trained, "mlflow.enabled=false", f"resume={trained}"))
