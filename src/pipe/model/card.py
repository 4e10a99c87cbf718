"""The model card: what prediction needs besides the weights, written with the model and read back typed.

It travels as the MLflow model's metadata. `CARD_VERSION` changes whenever a field changes meaning or is
added or removed; a card of another version is refused with a message saying what to do.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields
from typing import Any

from pipe import __version__
from pipe.errors import PipeError
from pipe.model.uncertainty import BandSettings

CARD_VERSION = 3   # 2: the prediction band (`band`); 3: the training parts' codes (`reference_codes`)


@dataclass(frozen=True)
class Units:
    """Units of the model's inputs and outputs."""

    length: str = "mm"   # point clouds, depth p_z, train_size_mm
    force: str = "N"
    time: str = "s"


@dataclass(frozen=True)
class BandCard:
    """The force band predict.py draws (`pipe.model.uncertainty`): its nominal level, the latent draws and
    their seed, and the widening calibrated on the validation parts at training time [N]."""

    level: float = 0.9
    samples: int = 64
    seed: int = 0
    offset_n: float = 0.0

    @property
    def settings(self) -> BandSettings:
        """The latent draws' settings, as `pipe.model.uncertainty` takes them."""
        return BandSettings(self.level, self.samples, self.seed)


@dataclass(frozen=True)
class ModelCard:
    domain: str                          # the domain the model was trained on
    points: int                          # points per cloud (Poisson-disk sampling)
    cloud_seed: int                      # seed of the sampling
    rate_hz: float                       # sample rate of the training profiles
    parameter_names: tuple[str, ...]     # Theta's parameters, in the dynamic model's order
    train_parts: tuple[str, ...]
    train_size_mm: tuple[float, float]   # smallest and largest extent of the training parts' clouds
    depth_scale_mm: float                # typical insertion depth of the training trials
    force_scale_n: float                 # typical peak force of the training trials
    band: BandCard = field(default_factory=BandCard)
    reference_codes: tuple[tuple[float, ...], ...] = ()   # the head's input of each training part (novelty)
    units: Units = field(default_factory=Units)
    pipe_version: str = __version__
    card_version: int = CARD_VERSION

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON/YAML types, as MLflow stores model metadata."""
        return json.loads(json.dumps(asdict(self)))          # tuples, nested ones too, become lists

    @classmethod
    def from_dict(cls, doc: dict[str, Any] | None, source: str) -> ModelCard:
        """Read a card back; refuse one of another version, or one that lacks or mistypes a field."""
        doc = dict(doc or {})
        version = doc.get("card_version")
        if version != CARD_VERSION:
            logged = f"model card version {version}" if version is not None else "no pipe model card"
            raise PipeError(f"the model at {source} has {logged} (logged by pipe {doc.get('pipe_version', '< 0.2')}), "
                            f"but this pipe {__version__} reads version {CARD_VERSION}: retrain the model with this "
                            "version, or predict with the pipe version that trained it")
        names = {f.name for f in fields(cls)}
        missing, unknown = sorted(names - set(doc)), sorted(set(doc) - names)
        if missing or unknown:
            raise PipeError(f"the model card at {source} is broken: missing {missing}, unknown {unknown}")
        try:
            card = cls(
                domain=str(doc["domain"]), points=int(doc["points"]), cloud_seed=int(doc["cloud_seed"]),
                rate_hz=float(doc["rate_hz"]), parameter_names=tuple(str(n) for n in doc["parameter_names"]),
                train_parts=tuple(str(n) for n in doc["train_parts"]),
                train_size_mm=(float(doc["train_size_mm"][0]), float(doc["train_size_mm"][1])),
                depth_scale_mm=float(doc["depth_scale_mm"]), force_scale_n=float(doc["force_scale_n"]),
                band=BandCard(level=float(doc["band"]["level"]), samples=int(doc["band"]["samples"]),
                              seed=int(doc["band"]["seed"]), offset_n=float(doc["band"]["offset_n"])),
                reference_codes=tuple(tuple(float(x) for x in row) for row in doc["reference_codes"]),
                units=Units(**doc["units"]), pipe_version=str(doc["pipe_version"]), card_version=int(version))
        except (TypeError, ValueError, IndexError, KeyError) as exc:
            raise PipeError(f"the model card at {source} is broken ({type(exc).__name__}: {exc})") from None
        codes = card.reference_codes
        if codes and (len(codes) != len(card.train_parts) or len({len(row) for row in codes}) != 1):
            raise PipeError(f"the model card at {source} is broken: reference_codes holds {len(codes)} rows of sizes "
                            f"{sorted({len(row) for row in codes})} for {len(card.train_parts)} training parts")
        return card
