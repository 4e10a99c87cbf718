"""The cloud's cross-section from its mating end: a code made by hand beside the encoder's (`code.sections`).

The encoder's 32 numbers keep what reconstructing the cloud needs and lose the small features that shape the
insertion force: a pin's lead-in and taper are read from them with R^2 0.49 and 0.19, from this descriptor
with 0.96 and 0.94 (docs/experiments.md, "The cloud's cross-section beside the code"). It is the part's length
and, for reaches from its lowest point (the mating end: parts are inserted along -z), the half-widths of the
points within that reach, as logs. Standardised over the training parts, it is appended to the encoder's code;
it has no spread, so PIPE's band draws nothing for it.
"""

from __future__ import annotations

import torch

from pipe.model.standardiser import Standardiser

TIP_REACHES_MM = (0.02, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0)   # from the mating end: lead-ins, chamfers, contacts
LENGTH_FRACTIONS = (0.25, 0.5, 0.75, 1.0)                     # of the part's length: tapers, shells, bodies
SECTION_SIZE = 1 + 2 * (len(TIP_REACHES_MM) + len(LENGTH_FRACTIONS))
MIN_WIDTH_MM = 1e-3          # a reach holding a single point on the axis has no width; its log is floored here


def section_descriptor(points: torch.Tensor) -> torch.Tensor:
    """Descriptors (B, SECTION_SIZE) of clouds (B, n, 3) in mm with the insertion axis along z and the mating end
    lowest: log length, then per reach (TIP_REACHES_MM, then LENGTH_FRACTIONS of the length) the logs of the
    larger and the smaller of max |x| and max |y| over the points within it (sorted, so a quarter turn about
    the axis changes nothing)."""
    points = points.double()
    height = points[..., 2] - points[..., 2].amin(dim=1, keepdim=True)            # (B, n) from the mating end
    length = height.amax(dim=1)
    reaches = torch.cat([torch.tensor(TIP_REACHES_MM, dtype=points.dtype).expand(len(points), -1),
                         length[:, None] * torch.tensor(LENGTH_FRACTIONS, dtype=points.dtype)], dim=1)
    within = height[:, None, :] <= reaches[:, :, None] + 1e-6                      # (B, reaches, n)
    half = points[..., :2].abs()                                                   # (B, n, 2)
    widths = torch.where(within[..., None], half[:, None], torch.zeros((), dtype=points.dtype)).amax(dim=2)
    widths = widths.clamp_min(MIN_WIDTH_MM).sort(dim=-1, descending=True).values   # (B, reaches, 2)
    return torch.cat([length.clamp_min(MIN_WIDTH_MM).log()[:, None], widths.log().flatten(1)], dim=1)


class SectionCode(Standardiser):
    """Clouds -> their `section_descriptor` standardised by the training parts' (`Standardiser`)."""

    def __init__(self) -> None:
        super().__init__(SECTION_SIZE)

    @classmethod
    def fitted(cls, train_points: torch.Tensor) -> SectionCode:
        """Standardised by the training parts' clouds (B, n, 3) in mm; needs two of them for a spread."""
        code = cls()
        code.fit(section_descriptor(train_points), "sections")
        return code

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """Codes (B, SECTION_SIZE), float32, of clouds (B, n, 3) in mm."""
        return self.standardise(section_descriptor(points))
