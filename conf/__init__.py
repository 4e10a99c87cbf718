"""pipe's Hydra configs (installed as pipe.conf). Hydra imports this package to read them; importing it
registers the resolvers the configs use: `numbered_split` (`pipe.data.domain.numbered_split`) for domains
over a numbered set of parts, e.g. a generated family (conf/domain/curve.yaml)."""

from omegaconf import OmegaConf

from pipe.data.domain import numbered_split

OmegaConf.register_new_resolver("numbered_split", numbered_split, replace=True)
