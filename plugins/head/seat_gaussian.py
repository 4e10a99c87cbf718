"""The paper's Gaussian head with its local models placed in millimetres before the trajectory's deepest point.

The paper's head tiles [0, max|p_z|] in fractions, so a feature that lies a fixed distance before the seat
(a pin's lead-in at the hole's mouth, a plug's detent) sits at another fraction in every part and every trial,
since max|p_z| holds the trial's gap and overtravel too (docs/experiments.md, "Trials aligned on their final
depth"). Here the sections are lengths in mm counted back from max|p_z|:
    l_i = softplus(s_i + SOFTPLUS_ONE) * section_mm     (neutral: every section section_mm long)
the shallowest section takes what the others leave of [0, max|p_z|], and where they reach past 0 all shrink in
proportion, so the sections still tile the depth range. Centres and widths follow from the sections as in
`pipe.plugins.head.gaussian`.
"""

from __future__ import annotations

import numpy as np
import torch
from torch.nn import functional as F

from pipe.model.interfaces import CompiledProfiles
from pipe.plugins.head.gaussian import SOFTPLUS_ONE, GaussianHead


class SeatGaussianHead(GaussianHead):
    def __init__(self, latent_dim: int, num_parameters: int, num_local_models: int = 10, hidden: int = 128,
                 edge_ratio_min: float = 1 / 20, edge_ratio_max: float = 1 / 3, section_mm: float = 1.0) -> None:
        super().__init__(latent_dim, num_parameters, num_local_models, hidden, edge_ratio_min, edge_ratio_max)
        if section_mm <= 0:
            raise ValueError(f"head.section_mm is a section's neutral length in mm: positive, not {section_mm}")
        self.section_mm = section_mm

    def sections(self, section: torch.Tensor, depth_max: torch.Tensor) -> torch.Tensor:
        """Lengths in mm counted back from max|p_z|; the shallowest section fills the rest of [0, max|p_z|]."""
        lengths = F.softplus(section + SOFTPLUS_ONE) * self.section_mm + 1e-6
        reach = depth_max.abs()[:, None, None]
        spare = torch.clamp(reach - lengths.sum(-1, keepdim=True), min=0.0)
        lengths = torch.cat([lengths[..., :1] + spare, lengths[..., 1:]], -1)
        return lengths * (reach / lengths.sum(-1, keepdim=True))     # a factor of 1 unless they overreach

    def compiled_free_profiles(self, depth: np.ndarray) -> CompiledProfiles | None:
        """None: the compiled kernels hold the paper's tiling; identification runs on torch."""
        return None
